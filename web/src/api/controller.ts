// The controller service's REST calls and job events (types generated from proto/schemas/controller).
import { requestJson } from './http';
import { withKeyQuery } from './key';

import type {
  JobAccepted,
  JobCreate,
  JobResult,
  JobStatus,
  PolicyJobCreate,
  PolicyJobResult,
  PolicyJobStatus,
  PolicyList,
  PolicyManifest,
  PolicyMetrics,
  PolicyProgressEvent,
  PolicyTaskInfo as PolicyTaskWire,
  PolicyTaskList,
  ProgressEvent,
  TaskInfo as TaskInfoWire,
  TaskList,
} from './controller.gen';

export type { JobAccepted, JobCreate, JobResult, JobStatus, ProgressEvent };
export type { PolicyJobCreate, PolicyJobResult, PolicyJobStatus, PolicyManifest, PolicyMetrics, PolicyProgressEvent };
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

/** A built-in policy task: the wire model names `name` and `model` (a task defines the rest); these
 * are read here. */
export interface PolicyTaskInfo extends PolicyTaskWire {
  description?: string;
  goal_variables?: string[];
  goal_low?: number[];
  goal_high?: number[];
  success_criterion?: string;
  episode_s?: number;
  timed?: boolean;
  target_state?: number[];
  /** `reward`: a dm_control suite task, judged by its return on MuJoCo (absent: a goal-reaching task). */
  kind?: 'reward';
  target_return?: number;
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

  // ---------------------------------------------------------------- policies
  async policyTasks(): Promise<PolicyTaskInfo[]> {
    const r = await requestJson<PolicyTaskList>('controller', this.base, '/policy-tasks');
    return r.tasks as PolicyTaskInfo[];
  }

  /** The stored policies (the latest version of each), of every model or of `model`. */
  async policies(model?: string): Promise<PolicyManifest[]> {
    const query = model ? `?model=${encodeURIComponent(model)}` : '';
    const r = await requestJson<PolicyList>('controller', this.base, `/policies${query}`);
    return r.policies;
  }

  submitPolicy(job: PolicyJobCreate): Promise<JobAccepted> {
    return requestJson('controller', this.base, '/policies', { method: 'POST', body: JSON.stringify(job) });
  }

  policyJob(id: string): Promise<PolicyJobStatus> {
    return requestJson('controller', this.base, `/policy-jobs/${encodeURIComponent(id)}`);
  }

  policyResult(id: string): Promise<PolicyJobResult> {
    return requestJson('controller', this.base, `/policy-jobs/${encodeURIComponent(id)}/result`);
  }

  async cancelPolicy(id: string): Promise<void> {
    await requestJson('controller', this.base, `/policy-jobs/${encodeURIComponent(id)}`, { method: 'DELETE' });
  }

  /** Server-sent events of a policy job: `status`, `progress` per iteration, then one `end`. */
  policyEvents(id: string): EventSource {
    return new EventSource(withKeyQuery(`${this.base}/policy-jobs/${encodeURIComponent(id)}/events`));
  }
}
