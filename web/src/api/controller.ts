// The controller service's REST calls and job events (types generated from proto/schemas/controller).
import { requestJson } from './http';
import { withKeyQuery } from './key';

import type {
  JobAccepted,
  JobCreate,
  JobResult,
  JobStatus,
  ProgressEvent,
  TaskInfo as TaskInfoWire,
  TaskList,
} from './controller.gen';

export type { JobAccepted, JobCreate, JobResult, JobStatus, ProgressEvent };
export type JobState = JobStatus['status'];
export const FINAL_STATES: readonly JobState[] = ['succeeded', 'failed', 'cancelled'];

/** A built-in task: the wire model names only `name` (a task defines the rest); these are read here. */
export interface TaskInfo extends TaskInfoWire {
  model?: string;
  description?: string;
  horizon?: number;
  points_per_step?: number;
  initial_state?: number[];
  target_state?: number[];
  initial_controls?: number[];
}

/** Control variables a task optimises: its points per control (round(horizon · points per step)) times
 * its controls; Infinity when the task does not say. */
export function controlVariables(task: TaskInfo): number {
  const { horizon, points_per_step: perStep, initial_controls: controls } = task;
  if (horizon === undefined || perStep === undefined || !controls?.length) return Infinity;
  return Math.max(1, Math.round(horizon * perStep)) * controls.length;
}

/** The task a page opens with: the one asked for by name, else the smallest problem the service
 * lists (fewest control variables: the job that finishes first), else the first listed. */
export function defaultTask(tasks: TaskInfo[], wanted: string | null): TaskInfo | undefined {
  const asked = tasks.find((t) => t.name === wanted);
  if (asked) return asked;
  let best = tasks[0];
  for (const t of tasks) if (best && controlVariables(t) < controlVariables(best)) best = t;
  return best;
}

export class ControllerApi {
  constructor(readonly base: string) {}

  ready(): Promise<Record<string, unknown>> {
    return requestJson('controller', this.base, '/readyz');
  }

  async tasks(): Promise<TaskInfo[]> {
    const r = await requestJson<TaskList>('controller', this.base, '/tasks');
    return r.tasks as TaskInfo[];
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
    return new EventSource(withKeyQuery(`${this.base}/jobs/${encodeURIComponent(id)}/events`));
  }
}
