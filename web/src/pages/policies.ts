// Policies: drive a stored policy (policydrive.ts: a session driven by it beside its MuJoCo ghost, its
// goal dragged in the view) and, below, train one for a built-in policy task (policytrain.ts: the job
// live to its stored policy, then "Drive it"). The address may name the policy to drive and start it:
// #/policies?policy=lander/lander-landing&drive=1 (and seed=N: the same start every time), and the
// task to train: #/policies?task=truck-parking.
import type { PolicyManifest } from '../api/controller';
import { h } from '../ui/dom';
import type { Page } from './context';
import { DrivePanel } from './policydrive';
import { TrainPanel } from './policytrain';

/** What the page's address asks for: the policy to select ("model/name"), whether to start driving it
 * at once, and the task to train. */
export function policiesQuery(query: string): { policy: string | null; drive: boolean; task: string | null } {
  const q = new URLSearchParams(query);
  return { policy: q.get('policy'), drive: q.get('drive') === '1', task: q.get('task') };
}

export const policiesPage: Page = (root, ctx) => {
  const drive = new DrivePanel(ctx);
  const toDrive = (p: PolicyManifest): void => {
    void drive.refresh(`${p.model}/${p.name}`).then(() => drive.start());
    root.scrollIntoView({ behavior: 'smooth', block: 'start' });
  };
  const train = new TrainPanel(ctx, toDrive);
  root.append(
    h('h1', {}, 'Policies'),
    h('section', { class: 'policy-drive', id: 'policy-drive' }, h('h2', {}, 'Drive a policy'), h('div', { class: 'split' }, drive.aside, drive.stage)),
    train.el,
  );
  const asked = policiesQuery(location.hash.split('?')[1] ?? '');
  void drive.open(asked.policy, asked.drive);
  void train.open(asked.task);
  return () => {
    drive.dispose();
    train.dispose();
  };
};
