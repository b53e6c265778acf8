// The controller service's REST calls and job events (its wire models: neuroanimator/controller_schemas.py).
import { requestJson } from './http';

export type JobState = 'queued' | 'running' | 'succeeded' | 'failed' | 'cancelled';
export const FINAL_STATES: readonly JobState[] = ['succeeded', 'failed', 'cancelled'];

export interface TaskInfo {
  name: string;
  model?: string;
  description?: string;
  horizon?: number;
  initial_state?: number[];
  target_state?: number[];
  [key: string]: unknown;
}

export interface JobCreate {
  task: string;
  target_state?: number[];
  initial_state?: number[];
  idempotency_key?: string;
}

export interface JobAccepted {
  id: string;
  status: JobState;
}

export interface JobStatus {
  id: string;
  status: JobState;
  task?: string | null;
  model?: string | null;
  iteration: number;
  max_iterations?: number | null;
  objective_history: (number | null)[];
  best_objective?: number | null;
  error?: string | null;
}

export interface ProgressEvent {
  iteration: number;
  objective?: number | null;
  best_objective?: number | null;
  success_emulator?: boolean | null;
  elapsed_s?: number | null;
}

export interface Trajectory {
  states: (number | null)[][];
}

export interface JobResult {
  id: string;
  status: 'succeeded' | 'failed' | 'cancelled';
  reason?: string | null;
  model?: string | null;
  version?: string | null;
  times?: number[] | null;
  controls?: unknown[] | null;
  emulated?: Trajectory | null;
  physical?: Trajectory | null;
  final_error_emulator?: number | null;
  final_error_physics?: number | null;
  success_emulator?: boolean | null;
  success_physics?: boolean | null;
  target_state?: (number | null)[] | null;
  initial_state?: (number | null)[] | null;
  state_labels?: string[] | null;
  iterations?: number | null;
}

export class ControllerApi {
  constructor(readonly base: string) {}

  ready(): Promise<Record<string, unknown>> {
    return requestJson('controller', this.base, '/readyz');
  }

  async tasks(): Promise<TaskInfo[]> {
    const r = await requestJson<{ tasks: TaskInfo[] } | TaskInfo[]>('controller', this.base, '/tasks');
    return Array.isArray(r) ? r : r.tasks;
  }

  submit(job: JobCreate): Promise<JobAccepted> {
    return requestJson('controller', this.base, '/jobs', { method: 'POST', body: JSON.stringify(job) });
  }

  job(id: string): Promise<JobStatus> {
    return requestJson('controller', this.base, `/jobs/${encodeURIComponent(id)}`);
  }

  result(id: string): Promise<JobResult> {
    return requestJson('controller', this.base, `/jobs/${encodeURIComponent(id)}/result`);
  }

  async cancel(id: string): Promise<void> {
    await requestJson('controller', this.base, `/jobs/${encodeURIComponent(id)}`, { method: 'DELETE' });
  }

  /** Server-sent events of a job: `progress` per iteration, then one `end`. */
  events(id: string): EventSource {
    return new EventSource(`${this.base}/jobs/${encodeURIComponent(id)}/events`);
  }
}
