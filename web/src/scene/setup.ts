// Helpers shared by the pages that draw models.
import type { ModelGeometry } from '../api/emulator.gen';
import { h } from '../ui/dom';
import { notify } from '../ui/notices';
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

/** Where to put the ground and the camera for a model at its rest poses. */
export function staging(g: ModelGeometry, poses: number[][] = g.rest_poses): { ground: number; center: number[]; radius: number } {
  const zs = poses.map((p) => p[2] ?? 0);
  const minZ = zs.length ? Math.min(...zs) : 0;
  const extent = g.extent > 0 ? g.extent : 1;
  const first = poses[0] ?? [0, 0, 0];
  return {
    ground: minZ >= 0 ? 0 : minZ - 0.6 * extent,
    center: [first[0] ?? 0, first[1] ?? 0, first[2] ?? 0],
    radius: Math.max(1.5 * extent, 2),
  };
}
