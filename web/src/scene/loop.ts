// One requestAnimationFrame loop for every view on the page, with a frame counter: window.__neuro
// holds {frames, fps} (fps over the last second), which the end-to-end test reads.

type Tick = (now: number) => void;

interface FrameStats {
  frames: number;
  fps: number;
}

declare global {
  interface Window {
    __neuro?: FrameStats;
  }
}

const ticks = new Set<Tick>();
const stats: FrameStats = { frames: 0, fps: 0 };
let running = false;
let windowStart = 0;
let windowFrames = 0;

function frame(now: number): void {
  stats.frames += 1;
  windowFrames += 1;
  if (now - windowStart >= 1000) {
    stats.fps = (windowFrames * 1000) / (now - windowStart);
    windowStart = now;
    windowFrames = 0;
  }
  for (const t of ticks) t(now);
  if (ticks.size) requestAnimationFrame(frame);
  else running = false;
}

export function onFrame(t: Tick): () => void {
  ticks.add(t);
  window.__neuro = stats;
  if (!running) {
    running = true;
    windowStart = performance.now();
    windowFrames = 0;
    requestAnimationFrame(frame);
  }
  return () => ticks.delete(t);
}
