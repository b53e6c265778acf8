// One requestAnimationFrame loop for every view on the page, with a frame counter and the resolution
// governor (quality.ts): window.__neuro holds {frames, fps, scale} (fps over the last second; scale:
// the share of the device pixels the views draw), which the status lines and end-to-end tests read.
import { ResolutionGovernor } from './quality';

type Tick = (now: number) => void;

interface FrameStats {
  frames: number;
  fps: number;
  scale: number;
}

declare global {
  interface Window {
    __neuro?: FrameStats;
  }
}

const ticks = new Set<Tick>();
const stats: FrameStats = { frames: 0, fps: 0, scale: 1 };
const governor = new ResolutionGovernor();
let running = false;
let last = 0;

function frame(now: number): void {
  stats.frames += 1;
  // a gap of more than half a second is a pause (hidden tab, a breakpoint), not slow drawing
  if (now - last > 500) governor.reset();
  last = now;
  governor.frame(now);
  stats.fps = governor.fps;
  stats.scale = resolutionScale();
  for (const t of ticks) t(now);
  if (ticks.size) requestAnimationFrame(frame);
  else running = false;
}

let pinned = false;

/** The resolution scale the views should draw at now (1: every device pixel). */
export function resolutionScale(): number {
  return pinned ? 1 : governor.scale;
}

/** Draw at full resolution whatever the frame rate (`?resolution=full` in the page's address: for
 * screenshots and recordings), or let the governor choose again. */
export function pinFullResolution(on: boolean): void {
  pinned = on;
}

export function onFrame(t: Tick): () => void {
  ticks.add(t);
  window.__neuro = stats;
  if (!running) {
    running = true;
    last = performance.now();
    governor.reset();
    requestAnimationFrame(frame);
  }
  return () => ticks.delete(t);
}
