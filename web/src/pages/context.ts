import type { ControllerApi } from '../api/controller';
import type { EmulatorApi } from '../api/emulator';

export interface Ctx {
  emulator: EmulatorApi;
  controller: ControllerApi;
}

/** A page draws itself into `root` and returns what tears it down (sockets, views, listeners). */
export type Page = (root: HTMLElement, ctx: Ctx) => () => void;
