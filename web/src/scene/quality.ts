// Graceful degradation: when frames come slower than the display wants (a loaded machine, software
// WebGL), draw fewer pixels. The governor watches the frame rate over windows of two seconds and steps
// the resolution scale down (to `min`) while frames are being dropped (more than three vsyncs missed in
// a window), and back up after the rate has stayed at the display's (at most one missed) for a while.
//
// Why it aims at the display's rate and not at "fast enough": a frame that misses a vsync waits for
// the next, so a view that needs 17 ms a frame shows 30-55 fps, not 58; stepping down only under 45 fps
// left such a view at scale 1 and never at 60. Aiming at 60 risks flicker instead (a scale just too
// slow, stepped up to, dropped from, stepped up to again), so each scale that proved too slow is tried
// again only after twice as long as the last time (a back-off, as adaptive video players do).

export interface GovernorOptions {
  low?: number; // fps under which the scale steps down (frames are being dropped)
  high?: number; // fps at or over which a window counts as good (the display's rate, less one frame)
  step?: number; // factor per step down (up: its inverse)
  min?: number;
  windowMs?: number;
  upAfter?: number; // good windows in a row before stepping up to a scale not yet found too slow
  maxUpAfter?: number; // the longest wait, in windows, before trying a scale found too slow again
}

export class ResolutionGovernor {
  scale = 1;
  fps = 0;
  private readonly o: Required<GovernorOptions>;
  private start = -1;
  private frames = 0;
  private good = 0;
  /** Per scale: how many times stepping up to it dropped frames (its wait doubles each time). */
  private readonly failures = new Map<number, number>();
  private sinceUp = Infinity; // windows since the last step up

  constructor(opts: GovernorOptions = {}) {
    this.o = { low: 58.5, high: 59.5, step: 0.8, min: 0.4, windowMs: 2000, upAfter: 3, maxUpAfter: 60, ...opts };
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
    this.sinceUp += 1;
    const before = this.scale;
    if (this.fps < this.o.low) {
      // dropped frames soon after a step up: the scale stepped up to is too slow for now
      if (this.sinceUp <= 2) this.failures.set(this.scale, (this.failures.get(this.scale) ?? 0) + 1);
      this.good = 0;
      this.scale = Math.max(this.o.min, round(this.scale * this.o.step));
    } else if (this.fps >= this.o.high && this.scale < 1) {
      this.good += 1;
      const up = Math.min(1, round(this.scale / this.o.step));
      if (this.good >= this.waitFor(up)) {
        this.good = 0;
        this.sinceUp = 0;
        this.scale = up;
      }
    } else {
      this.good = 0;
    }
    return this.scale !== before;
  }

  /** Good windows in a row before stepping up to `scale`: `upAfter`, doubled for each time that scale
   * proved too slow, up to `maxUpAfter`. */
  waitFor(scale: number): number {
    return Math.min(this.o.maxUpAfter, this.o.upAfter * 2 ** (this.failures.get(scale) ?? 0));
  }

  /** Forget the timing (after a pause, e.g. a hidden tab), keeping the scale and what proved too slow. */
  reset(): void {
    this.start = -1;
    this.frames = 0;
    this.good = 0;
  }
}

function round(v: number): number {
  return Math.round(v * 1000) / 1000;
}
