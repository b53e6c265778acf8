// The trainer service's calls (types generated from proto/schemas/trainer in trainer.gen.ts): upload a
// model to train (a multipart form), follow a training (its status, its server-sent events), cancel it.
import { jsonOf, requestJson, send } from './http';
import { withKeyQuery } from './key';
import type { TrainingAccepted, TrainingResult, TrainingStatus } from './trainer.gen';

export type { TrainingAccepted, TrainingResult, TrainingStatus };

export class TrainerApi {
  constructor(readonly base: string) {}

  ready(): Promise<Record<string, unknown>> {
    return requestJson('trainer', this.base, '/readyz');
  }

  /** POST /trainings: the file and the form's fields (TrainingOptions, as text). The model is checked
   * before this answers: a refusal is a ServiceError whose `detail` says what is wrong with it. */
  async upload(file: Blob, filename: string, fields: Record<string, string>): Promise<TrainingAccepted> {
    const form = new FormData();
    for (const [k, v] of Object.entries(fields)) form.append(k, v);
    form.append('file', file, filename);
    const r = await send('trainer', this.base, '/trainings', { method: 'POST', body: form, headers: { Accept: 'application/json' } });
    return jsonOf<TrainingAccepted>('trainer', r);
  }

  training(id: string): Promise<TrainingStatus> {
    return requestJson('trainer', this.base, `/trainings/${encodeURIComponent(id)}`);
  }

  cancel(id: string): Promise<TrainingStatus> {
    return requestJson('trainer', this.base, `/trainings/${encodeURIComponent(id)}`, { method: 'DELETE' });
  }

  /** Server-sent events of a training: `status`, `progress` (with new loss points), then one `end`. */
  events(id: string): EventSource {
    return new EventSource(withKeyQuery(`${this.base}/trainings/${encodeURIComponent(id)}/events`));
  }
}
