// The try-on service's HTTP API, as the viewer uses it (same origin, so plain fetch).
//
// Errors are RFC 9457 problem+json: every failed call throws an ApiError that carries the
// problem document ({title, status, detail, errors: [{pointer, detail}]}).

export class ApiError extends Error {
  constructor(problem) {
    super(problem.detail || problem.title);
    this.problem = problem;
  }
}

// The API key, when the deployment checks keys (GET /viewer/config.json says so and names the header).
const auth = { header: 'X-API-Key', key: '' };

export function setApiKey(header, key) {
  auth.header = header;
  auth.key = key;
}

function headers(extra = {}) {
  return auth.key ? { ...extra, [auth.header]: auth.key } : extra;
}

async function problemOf(response) {
  const type = response.headers.get('content-type') || '';
  if (type.includes('json')) {
    const body = await response.json();
    if (body && body.title) return new ApiError(body);
  }
  return new ApiError({ title: `HTTP ${response.status}`, status: response.status, detail: response.statusText });
}

async function call(url, init = {}) {
  let response;
  try {
    response = await fetch(url, { ...init, headers: headers(init.headers) });
  } catch (err) {
    if (err.name === 'AbortError') throw new ApiError({ title: 'Cancelled', status: 0, detail: `${url}: cancelled` });
    throw new ApiError({ title: 'Network error', status: 0, detail: `${url}: ${err.message}` });
  }
  if (!response.ok) throw await problemOf(response);
  return response;
}

export async function getJson(url) {
  return (await call(url, { headers: { Accept: 'application/json' } })).json();
}

function postJson(url, body, accept = 'application/json', signal = undefined) {
  return call(url, { method: 'POST', body: JSON.stringify(body), headers: { 'Content-Type': 'application/json', Accept: accept }, signal });
}

// POST /v1/bodies/fit: tape measurements (cm, optional kg and gender) -> {phenotypes, measurements, residuals, ...}.
export async function fitBody(measurements) {
  return (await postJson('/v1/bodies/fit', measurements)).json();
}

const GLB = 'model/gltf-binary';
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

// A 422 from POST /v1/drape that sends the client to POST /v1/jobs: the drape is estimated to
// outlast the request deadline, or has more frames than a synchronous drape may.
function wantsJob(err) {
  const p = err.problem || {};
  return p.status === 422 && [p.detail, ...(p.errors || []).map((e) => e.detail)].some((d) => (d || '').includes('/v1/jobs'));
}

// What the viewer shows of an answer: its figures from the headers, and the glb bytes.
async function result(response, via) {
  return {
    via,
    glb: await response.arrayBuffer(),
    serverTiming: response.headers.get('Server-Timing'),
    frames: response.headers.get('X-Frames'),
    cache: response.headers.get('X-Cache'),
    encoding: response.headers.get('Content-Encoding') || 'identity',
  };
}

// Drape `request` (a DrapeRequest, format glb). route: 'drape' (POST /v1/drape), 'job'
// (POST /v1/jobs) or 'auto' (a job when `frames` exceeds `maxFrames`, else the synchronous
// drape, and a job after all when that answers 422 pointing to /v1/jobs).
// onProgress({phase, fraction}) follows it; `signal` aborts (a job is then cancelled).
export async function drape(request, { route = 'auto', frames = 0, maxFrames = Infinity, onProgress = () => {}, signal } = {}) {
  if (route === 'job' || (route === 'auto' && frames > maxFrames)) return runJob(request, onProgress, signal);
  onProgress({ phase: 'draping', fraction: null });
  try {
    return await result(await postJson('/v1/drape', request, GLB, signal), 'POST /v1/drape');
  } catch (err) {
    if (route !== 'auto' || !wantsJob(err) || signal?.aborted) throw err;
    onProgress({ phase: 'too long for a synchronous drape: sent as a job', fraction: null });
    return runJob(request, onProgress, signal);
  }
}

// POST /v1/jobs (202 + Location), poll the job until it succeeds, then GET its result_url.
async function runJob(request, onProgress, signal) {
  const accepted = await postJson('/v1/jobs', request);
  const location = accepted.headers.get('Location');
  let job = await accepted.json();
  try {
    while (job.state === 'queued' || job.state === 'running') {
      onProgress({ phase: `job ${job.state}`, fraction: job.progress.fraction, job });
      await sleep(500);
      if (signal?.aborted) throw new ApiError({ title: 'Cancelled', status: 0, detail: `job ${job.id} cancelled` });
      job = await getJson(location);
    }
  } catch (err) {
    if (signal?.aborted) await call(location, { method: 'DELETE' }).catch(() => {});
    throw err;
  }
  if (job.state !== 'succeeded') {
    throw new ApiError(job.error || { title: `Job ${job.state}`, status: 0, detail: `job ${job.id} ${job.state}` });
  }
  onProgress({ phase: 'downloading the result', fraction: 1, job });
  const out = await result(await call(job.result_url, { headers: { Accept: GLB } }), `POST /v1/jobs (${job.id})`);
  out.jobSeconds = job.finished_at - job.created_at;
  return out;
}

// "shape;dur=4.9, arms;dur=87.8, ..." -> [{name: 'shape', ms: 4.9}, ...] (RFC: W3C Server Timing).
export function parseServerTiming(header) {
  if (!header) return [];
  return header.split(',').map((entry) => {
    const [name, ...params] = entry.trim().split(';');
    const dur = params.map((p) => p.trim().split('=')).find(([k]) => k === 'dur');
    return { name, ms: dur ? Number(dur[1]) : null };
  });
}
