import { afterEach, describe, expect, it } from 'vitest';
import { describeFailure } from '../src/api/http';
import { apiKey, setApiKey, withKeyHeader, withKeyQuery } from '../src/api/key';

describe('the API key', () => {
  afterEach(() => setApiKey(null));

  it('adds nothing while no key is set', () => {
    expect(apiKey()).toBeNull();
    expect(withKeyHeader({ Accept: 'application/json' }).has('Authorization')).toBe(false);
    expect(withKeyQuery('ws://h/ws/sessions/a?mode=realtime')).toBe('ws://h/ws/sessions/a?mode=realtime');
  });

  it('goes as a bearer header on calls and as api_key on sockets and event streams', () => {
    setApiKey('  k&1 ');
    expect(apiKey()).toBe('k&1');
    const headers = withKeyHeader({ Accept: 'application/json' });
    expect(headers.get('Authorization')).toBe('Bearer k&1');
    expect(headers.get('Accept')).toBe('application/json');
    expect(withKeyQuery('ws://h/ws/sessions/a?mode=realtime')).toBe('ws://h/ws/sessions/a?mode=realtime&api_key=k%261');
    expect(withKeyQuery('http://h/jobs/j/events')).toBe('http://h/jobs/j/events?api_key=k%261');
    expect(withKeyHeader({ Authorization: 'Bearer other' }).get('Authorization')).toBe('Bearer other');
  });

  it('is forgotten when cleared, and a 401 says where to enter one', () => {
    setApiKey('k');
    setApiKey('');
    expect(apiKey()).toBeNull();
    const e = describeFailure('emulator', 401, 'Unauthorized', { error: 'unauthorized', message: 'an API key is required' });
    expect(e.message).toContain('an API key is required');
    expect(e.message).toContain('key button');
  });
});
