// Graceful degradation: when frames come slower than the display wants (a loaded machine, software
// WebGL), draw fewer pixels. The governor watches the frame rate over windows of about a second and
// steps the resolution scale down (to `min`) while it is low, and back up after it has stayed high.

export interface GovernorOptions {
  low?: number; // fps under which the scale steps down
  high?: number; // fps over which it may step back up
  step?: number; // factor per step down (up: its inverse)
  min?: number;
  windowMs?: number;
  upAfter?: number; // good windows in a row before stepping up
}

export class ResolutionGovernor {
  scale = 1;
  fps = 0;
  private readonly o: Required<GovernorOptions>;
  private start = -1;
  private frames = 0;
  private good = 0;

  constructor(opts: GovernorOptions = {}) {
    this.o = { low: 45, high: 57, step: 0.8, min: 0.4, windowMs: 1000, upAfter: 3, ...opts };
  }

  /** Count one frame drawn at time `now` (ms); returns true when the scale changed. */
  frame(now: number): boolean {
    if (this.start < 0) {
      this.start = now;
      return false;
    }
    this.frames += 1;
    const span = now - this.start;
    if (span < this.o.windowMs) return false;
    this.fps = (this.frames * 1000) / span;
    this.start = now;
    this.frames = 0;
    const before = this.scale;
    if (this.fps < this.o.low) {
      this.good = 0;
      this.scale = Math.max(this.o.min, round(this.scale * this.o.step));
    } else if (this.fps >= this.o.high && this.scale < 1) {
      this.good += 1;
      if (this.good >= this.o.upAfter) {
        this.good = 0;
        this.scale = Math.min(1, round(this.scale / this.o.step));
      }
    } else {
      this.good = 0;
    }
    return this.scale !== before;
  }

  /** Forget the timing (after a pause, e.g. a hidden tab), keeping the scale. */
  reset(): void {
    this.start = -1;
    this.frames = 0;
    this.good = 0;
  }
}

function round(v: number): number {
  return Math.round(v * 1000) / 1000;
}
