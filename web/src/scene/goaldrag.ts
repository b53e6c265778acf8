// Dragging a goal in a view with the pointer: pressed on one of the goal's objects, the goal follows
// the pointer on the horizontal plane through the point it was picked at (MuJoCo's z = const: the
// ground for a pad or a parking spot, the target's height for a goal in the air), while the camera
// holds still; `moved` hears every position, `done` the last one.
import * as THREE from 'three';
import type { Viewer } from './viewer';

export interface GoalDrag {
  /** The objects that pick the goal (null: no goal to drag now). */
  targets: () => THREE.Object3D[] | null;
  /** Where the goal is now (MuJoCo's frame): the plane of the drag goes through its z. */
  at: () => [number, number, number] | null;
  /** The goal dragged to (x, y) on its plane (while the pointer moves). */
  moved: (x: number, y: number) => void;
  /** The pointer let go at (x, y). */
  done: (x: number, y: number) => void;
  /** The drag began (the page stops its camera following). */
  began?: () => void;
}

/** Listens on the view's canvas; returns what stops listening. */
export function dragGoal(viewer: Viewer, d: GoalDrag): () => void {
  const canvas = viewer.renderer.domElement;
  const ray = new THREE.Raycaster();
  let active: { plane: THREE.Plane; grab: THREE.Vector3; from: [number, number]; last: [number, number]; pointer: number } | null = null;

  const setRay = (ev: PointerEvent): void => {
    const r = canvas.getBoundingClientRect();
    ray.setFromCamera(new THREE.Vector2(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1), viewer.camera);
  };
  // the ray in MuJoCo's frame (the `world` group), where the plane is z = const
  const onPlane = (plane: THREE.Plane): THREE.Vector3 | null => {
    viewer.world.updateMatrixWorld();
    const local = ray.ray.clone().applyMatrix4(viewer.world.matrixWorld.clone().invert());
    return local.intersectPlane(plane, new THREE.Vector3());
  };

  const down = (ev: PointerEvent): void => {
    const targets = d.targets();
    const at = d.at();
    if (!targets?.length || !at || ev.button !== 0) return;
    setRay(ev);
    if (!ray.intersectObjects(targets, true).length) return;
    const plane = new THREE.Plane(new THREE.Vector3(0, 0, 1), -at[2]);
    const grab = onPlane(plane);
    if (!grab) return;
    active = { plane, grab, from: [at[0], at[1]], last: [at[0], at[1]], pointer: ev.pointerId };
    viewer.controls.enabled = false;
    canvas.setPointerCapture(ev.pointerId);
    canvas.classList.add('dragging');
    d.began?.();
    ev.preventDefault();
    ev.stopImmediatePropagation();
  };
  const move = (ev: PointerEvent): void => {
    if (!active || ev.pointerId !== active.pointer) return;
    setRay(ev);
    const p = onPlane(active.plane);
    if (!p) return;
    active.last = [active.from[0] + p.x - active.grab.x, active.from[1] + p.y - active.grab.y];
    d.moved(...active.last);
  };
  const up = (ev: PointerEvent): void => {
    if (!active || ev.pointerId !== active.pointer) return;
    const a = active;
    active = null;
    viewer.controls.enabled = true;
    canvas.classList.remove('dragging');
    if (canvas.hasPointerCapture(ev.pointerId)) canvas.releasePointerCapture(ev.pointerId);
    d.done(...a.last);
  };
  // before OrbitControls' own listener (registered when the view was made), so a goal press never orbits
  canvas.addEventListener('pointerdown', down, { capture: true });
  canvas.addEventListener('pointermove', move);
  canvas.addEventListener('pointerup', up);
  canvas.addEventListener('pointercancel', up);
  return () => {
    canvas.removeEventListener('pointerdown', down, { capture: true });
    canvas.removeEventListener('pointermove', move);
    canvas.removeEventListener('pointerup', up);
    canvas.removeEventListener('pointercancel', up);
  };
}
