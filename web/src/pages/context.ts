import type { ControllerApi } from '../api/controller';
import type { EmulatorApi } from '../api/emulator';
import type { TrainerApi } from '../api/trainer';

export interface Ctx {
  emulator: EmulatorApi;
  controller: ControllerApi;
  /** null when the deployment has no trainer service. */
  trainer: TrainerApi | null;
}

/** A page draws itself into `root` and returns what tears it down (sockets, views, listeners). */
export type Page = (root: HTMLElement, ctx: Ctx) => () => void;
