import { afterEach, describe, expect, it, vi } from 'vitest';
import { loadBench, loadEval, measuredFiles, timeToReach } from '../src/api/measurements';

describe('measurements', () => {
  afterEach(() => vi.unstubAllGlobals());

  it('asks only for the results the server lists (an uploaded model has no benchmark)', async () => {
    const asked: string[] = [];
    vi.stubGlobal('fetch', async (url: string) => {
      asked.push(url);
      if (url === 'artifacts/upload') return new Response(JSON.stringify({ model: 'upload', measured: ['eval.json'] }));
      if (url === 'artifacts/upload/eval.json') return new Response(JSON.stringify({ model: 'upload', by_substeps: [] }));
      return new Response('{}', { status: 404 });
    });
    const measured = await measuredFiles('upload');
    expect(measured).toEqual(['eval.json']);
    expect(await loadBench('upload', measured)).toBeNull();
    expect(await loadEval('upload', measured)).not.toBeNull();
    expect(asked).toEqual(['artifacts/upload', 'artifacts/upload/eval.json']);
  });

  it('tells when a rollout error reaches a level', () => {
    const curve = { t: [0, 1, 2, 3], error: [0, 0.05, 0.5, 1.5] };
    expect(timeToReach(curve, 0.1)).toBeCloseTo(1 + 0.05 / 0.45);
    expect(timeToReach(curve, 1)).toBeCloseTo(2.5);
    expect(timeToReach(curve, 2)).toBeNull();
  });
});
