import { describe, expect, it } from 'vitest';
import { SPEC_PLACEHOLDER, SPEC_REFUSED, specProblem, specRefused } from '../src/training/operating';
import { formFields, type UploadForm } from '../src/training/progress';

const blank: UploadForm = { name: '', superStep: '', examples: '', epochs: '', hidden: '', rolloutSteps: '', entry: '', force: false };

describe("the Add a model panel's operating spec", () => {
  it('sends the spec as typed, and none when the box is blank', () => {
    const spec = '{"keyframe": "hover"}';
    expect(formFields({ ...blank, operatingSpec: `  ${spec}\n` })).toEqual({ super_step: 'auto', operating_spec: spec });
    expect(formFields({ ...blank, operatingSpec: ' \n ' })).toEqual({ super_step: 'auto' });
    expect(formFields(blank)).toEqual({ super_step: 'auto' });
  });

  it('names what is not JSON, or not an object, before anything is sent', () => {
    expect(specProblem('')).toBeNull();
    expect(specProblem('{"controls": {"thrust1": {"range": [2, 5]}}}')).toBeNull();
    expect(specProblem(SPEC_PLACEHOLDER)).toBeNull(); // the example it shows is a spec
    expect(specProblem('{"controls": {')).toMatch(/^The operating spec is not JSON: /);
    expect(specProblem('[1, 2]')).toMatch(/is a JSON object/);
    expect(specProblem('null')).toMatch(/is a JSON object/);
  });

  it("tells the trainer's refusal of the spec from a refusal of the model", () => {
    expect(specRefused(SPEC_REFUSED, '{"controls": {"thrust9": {}}}')).toBe(true);
    expect(specRefused('no_ctrlrange', '{"controls": {}}')).toBe(false);
    expect(specRefused(SPEC_REFUSED, '')).toBe(false); // the archive's operating.json: a refusal of the upload
  });
});
