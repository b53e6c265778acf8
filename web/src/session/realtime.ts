// A real-time websocket to one emulator session (`?mode=realtime&poses=true`): the server steps every
// Δt with the latest controls and sends each state with its bodies' poses (and the MuJoCo twin's with
// `shadow`). Poses go into snapshot buffers sampled at the display rate, one period behind.
import type { ServerMessage, WsState } from '../api/emulator.gen';
import { lerpPoses, SnapshotBuffer, type Pose } from '../scene/interp';

/**
 * Whether a state left what the emulator was trained on, in words, from the `outside_envelope` field of
 * a state message when the emulator service sends one (true, or the groups or variables outside, or a
 * message); null when the state is inside or the service does not say.
 */
export function envelopeText(msg: object): string | null {
  const v = (msg as Record<string, unknown>).outside_envelope;
  if (v === undefined || v === null || v === false) return null;
  if (Array.isArray(v)) return v.length ? `outside the trained range of ${v.map(String).join(', ')}` : null;
  if (typeof v === 'string') return v || null;
  if (typeof v === 'object') {
    const keys = Object.entries(v as Record<string, unknown>)
      .filter(([, x]) => x)
      .map(([k]) => k);
    return keys.length ? `outside the trained range of ${keys.join(', ')}` : null;
  }
  return 'outside the range of states the emulator was trained on';
}

export interface RealtimeHandlers {
  onState?: (msg: WsState) => void;
  onError?: (message: string, code: string) => void;
  onClose?: (reason: string) => void;
}

export class RealtimeSession {
  readonly emulated = new SnapshotBuffer<Pose[]>(lerpPoses);
  readonly shadow = new SnapshotBuffer<Pose[]>(lerpPoses);
  periodMs = 500;
  last: WsState | null = null;
  states = 0;
  private ws: WebSocket;
  private closedByUs = false;
  private lastSent = '';

  constructor(
    url: string,
    private readonly handlers: RealtimeHandlers,
  ) {
    this.ws = new WebSocket(url);
    this.ws.onmessage = (ev) => this.onMessage(ev);
    this.ws.onclose = (ev) => {
      if (this.closedByUs) return;
      const why = ev.code === 4404 ? 'the session no longer exists (it expired or the service restarted)' : `the connection closed (code ${ev.code})`;
      handlers.onClose?.(`Lost the live session: ${why}. Start a new session.`);
    };
    this.ws.onerror = () => {
      /* the close event that follows says what happened */
    };
  }

  private onMessage(ev: MessageEvent): void {
    if (typeof ev.data !== 'string') return;
    const msg = JSON.parse(ev.data) as ServerMessage;
    if (msg.type === 'started') {
      this.periodMs = msg.period_s * 1000;
    } else if (msg.type === 'state') {
      const s = msg as WsState;
      const now = performance.now();
      this.states += 1;
      this.last = s;
      if (s.poses) this.emulated.push(now, s.poses);
      if (s.shadow?.poses) this.shadow.push(now, s.shadow.poses);
      this.handlers.onState?.(s);
    } else if (msg.type === 'error') {
      const text =
        msg.error === 'diverged'
          ? `The emulator diverged: ${msg.message} Start a new session.`
          : `The emulator reported a problem: ${msg.message}`;
      this.handlers.onError?.(text, msg.error);
    }
  }

  private send(obj: unknown): void {
    if (this.ws.readyState === WebSocket.OPEN) this.ws.send(JSON.stringify(obj));
  }

  /** The inputs held from now on; a driven session takes its driver's parameters (`driver`) and the
   * forces, its controls coming from the driver. Sent only when something changed. */
  setControls(controls: number[], forces: number[] = [], driver?: Record<string, number>): void {
    this.hold(driver ? { type: 'controls', controls, forces, driver } : { type: 'controls', controls, forces });
  }

  /** A policy-driven session's inputs from now on: its goal (G values) and the forces; its policy sets
   * the controls, so none are sent. Sent only when something changed. */
  setGoal(goal: number[], forces: number[] = []): void {
    this.hold({ type: 'controls', forces, goal });
  }

  private hold(msg: object): void {
    const text = JSON.stringify(msg);
    if (text === this.lastSent) return;
    if (this.ws.readyState !== WebSocket.OPEN) {
      this.ws.addEventListener('open', () => this.hold(msg), { once: true });
      return;
    }
    this.lastSent = text;
    this.ws.send(text);
  }

  setShadow(on: boolean): void {
    this.shadow.clear();
    const msg = { type: 'start', mode: 'realtime', shadow: on };
    if (this.ws.readyState === WebSocket.OPEN) this.send(msg);
    else this.ws.addEventListener('open', () => this.send(msg), { once: true });
  }

  /** Poses to draw now: one period behind the newest state, interpolated. */
  sample(now: number, buffer: SnapshotBuffer<Pose[]> = this.emulated): Pose[] | null {
    return buffer.sample(now - this.periodMs);
  }

  close(): void {
    this.closedByUs = true;
    this.ws.close();
  }
}
