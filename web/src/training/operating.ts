// The "Add a model" panel's operating spec (docs/operating-spec.md): where the model operates, as JSON
// the trainer service reads from the form field operating_spec. Pure functions: the panel checks the
// text before it sends it (a syntax error is named at once) and tells the trainer's refusal of a spec
// (error code invalid_operating_spec: a field that is not one, an actuator the model does not have, a
// band outside a ctrlrange, ...) from a refusal of the model, to show it beside the box.

/** The trainer's error code for an operating spec that is not one, or does not fit the model. */
export const SPEC_REFUSED = 'invalid_operating_spec';

/** What the empty box shows: a small spec of a drone that hovers (its keyframe and one thrust's band). */
export const SPEC_PLACEHOLDER = '{\n  "keyframe": "hover",\n  "controls": {"thrust1": {"centre": 3.25, "spread": 0.8}},\n  "held_share": 0.3\n}';

/** Why the text cannot be sent as an operating spec, or null (an empty box sends none: the trainer then
 * finds the operating point in the model). Only the JSON is checked here; the trainer checks the rest. */
export function specProblem(text: string): string | null {
  if (!text.trim()) return null;
  let value: unknown;
  try {
    value = JSON.parse(text);
  } catch (e) {
    return `The operating spec is not JSON: ${e instanceof Error ? e.message : String(e)}`;
  }
  if (value === null || typeof value !== 'object' || Array.isArray(value)) return 'The operating spec is a JSON object, e.g. {"keyframe": "hover"}.';
  return null;
}

/** Whether a refusal of the upload is the trainer's refusal of the operating spec the box sent. */
export function specRefused(code: string | null, sent: string): boolean {
  return code === SPEC_REFUSED && sent.trim() !== '';
}
