// Helpers shared by the pages that draw models.
import type { ModelGeometry } from '../api/emulator.gen';
import type { EmulatorApi } from '../api/emulator';
import { h } from '../ui/dom';
import { notify } from '../ui/notices';
import { MeshFiles } from './meshes';
import { Viewer, WebGLUnavailable } from './viewer';

/** A viewer in `host`, or null (with the reason shown in its place) when WebGL is unavailable. */
export function makeViewer(host: HTMLElement): Viewer | null {
  try {
    return new Viewer(host);
  } catch (e) {
    const text = e instanceof WebGLUnavailable ? e.message : `The 3D view could not start: ${String(e)}`;
    host.append(h('p', { class: 'error-text view-error' }, text));
    notify(text, 'warning', 'webgl');
    return null;
  }
}

/** Mesh files of a model version, from the emulator service (one loader per page: views share it). */
export function meshFilesOf(api: EmulatorApi, g: ModelGeometry): MeshFiles {
  return new MeshFiles((asset) => api.asset(g.model, asset, g.version));
}
