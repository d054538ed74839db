// MantissaCam web viewer: upload, (simulate,) reconstruct, watch the job, inspect the result.
// Plain browser JavaScript, no build step. Every request carries the API key (localStorage).
"use strict";

const $ = (id) => document.getElementById(id);
const KEY_STORAGE = "mcam-api-key";
// A job is polled after 250 ms, then 1.5 times later each time, up to every 2 s (a long
// job: 30 requests a minute). A failed poll is retried after 1, 2, 4, 8, 8… s, or after
// the Retry-After the server gave.
const POLL_FIRST_MS = 250;
const POLL_MAX_MS = 2000;
const RETRY_MAX_MS = 8000;
// A poll not answered within this long (a connection that died without closing, as on a
// network that changed) is given up and retried as a lost connection; it was waited
// for without end.
const POLL_TIMEOUT_MS = 20000;
// A result (a preview, the histogram, the EXR) of which no byte came for this long is
// given up the same way: it was waited for without end (the panels stood empty beside
// "succeeded" until Cancel). Longer than a poll's: the server may wait for a decode turn
// (MCAM_DECODE_WAIT_S, 10 s by default) and then render a 4096 x 4096 preview.
const RESULT_TIMEOUT_MS = 60000;
// A result the server is too busy to make (429, or 503 past MCAM_MAX_CONCURRENT_DECODES
// previews and uploads at once) is asked for again after Retry-After, this many times
// in all.
const RESULT_TRIES = 5;
const BUSY = [429, 503];
// Cancel pressed while an upload was in flight asks the server for the job the upload
// may have made (it may have received it whole) for at most this long while the server
// is still handling the upload (409) or cannot be reached.
const UPLOAD_LOOKUP_MS = 120000;
const FINISHED = ["succeeded", "failed", "cancelled"];
let shownJob = null; // the succeeded job whose results the panels show (null: none)
// The job in flight: { id, stop: AbortController, uploadKey: the Idempotency-Key of its
// upload (once sent), cancelling: a Cancel's promise (once pressed) }.
let watched = null;
let histogram = null;
let exposureTimer = null;
let inputNotes = []; // what the page notes of this run's input (the simulate's clipping)
let resultsBusyShown = false; // the status says a result is asked for again (resultsBusy)

// An API call that failed: the HTTP status (0: the server could not be reached), the
// seconds a 429 or 503 asked to wait (Retry-After), the error's code (null: none) and the
// parameters its message asks to give (form field names; none: []).
class ApiError extends Error {
  constructor(message, status = 0, retryAfterS = null, code = null, parameters = []) {
    super(message);
    this.status = status;
    this.retryAfterS = retryAfterS;
    this.code = code;
    this.parameters = parameters;
  }
}

function apiKey() {
  return localStorage.getItem(KEY_STORAGE) || "";
}

// Where on the page a missing or refused key is mended (the API's 401 names its header
// and files only).
const ENTER_KEY = "enter the key mcam serve printed on first start (also in its data " +
  "folder's api_keys) under API key at the top and press Save key";

async function replyError(reply) {
  let message = `${reply.status} ${reply.statusText}`;
  let code = null;
  let parameters = [];
  try {
    const body = await reply.json();
    message = `${body.code}: ${body.message}`;
    code = body.code;
    parameters = body.parameters || [];
  } catch (_) { /* not JSON: keep the status line */ }
  if (reply.status === 401) message += `; ${ENTER_KEY}`;
  const retryAfterS = Number(reply.headers.get("Retry-After")) || null;
  return new ApiError(message, reply.status, retryAfterS, code, parameters);
}

// An API key is sent in a header: visible ASCII only (a pasted zero-width space or dash
// made fetch refuse the request, which read as "cannot reach the server").
const KEY_PATTERN = /^[\x21-\x7e]*$/;

// The error of a request that reached no server.
const unreachable = () =>
  new ApiError("cannot reach the server; check that mcam serve is running");

async function api(path, options = {}) {
  if (!apiKey()) throw new ApiError(`no API key saved: ${ENTER_KEY}`, 401);
  if (!KEY_PATTERN.test(apiKey())) {
    throw new Error("the saved API key holds characters a key never has (a space, a " +
      "typographic dash?); paste it again as mcam serve printed it and save it");
  }
  const headers = { Authorization: `Bearer ${apiKey()}`, ...(options.headers || {}) };
  let reply;
  try {
    reply = await fetch(path, { ...options, headers });
  } catch (error) {
    if (error.name === "AbortError") throw error;
    throw unreachable();
  }
  if (!reply.ok) throw await replyError(reply);
  return reply;
}

// A wait of ms that ends early when signal (if any) aborts.
function sleep(ms, signal = null) {
  return new Promise((resolve) => {
    const onAbort = () => { clearTimeout(timer); resolve(); };
    const timer = setTimeout(() => { signal?.removeEventListener("abort", onAbort); resolve(); }, ms);
    signal?.addEventListener("abort", onAbort, { once: true });
  });
}

// How long to wait before asking again after the failures-th failure in a row.
function retryDelayMs(error, failures) {
  if (error.retryAfterS) return error.retryAfterS * 1000;
  return Math.min(1000 * 2 ** (failures - 1), RETRY_MAX_MS);
}

// "The server has no such thing (any more)": asking again will not help.
const isGone = (error) => error instanceof ApiError && [404, 410].includes(error.status);

// A client error that asking again will not mend (a key without the read scope, or
// revoked: 401, 403); not a timeout (408) or a rate limit (429).
const isFinal = (error) => error instanceof ApiError && error.status >= 400 &&
  error.status < 500 && ![408, 429].includes(error.status);

function retryNote(error, delayMs) {
  const reason = error.status
    ? `the server answered ${error.message}` : "connection to the server lost";
  return `${reason}; retrying in ${Math.ceil(delayMs / 1000)} s`;
}

// tone: "" (plain), "warning" (trouble that is being retried) or "error". The text is
// written only when it changed: the status is a live region, and each poll of a job
// wrote "job …: queued" again, which a screen reader read out again every 2 s.
function setStatus(text, tone = "") {
  if ($("status").textContent !== text) $("status").textContent = text;
  $("status").className = tone;
  resultsBusyShown = false;
}

// Disable the button id; the keyboard's focus on it goes to the job's status, which says
// what happens next (a disabled button dropped it to the page's body: Reconstruct or
// Cancel pressed from the keyboard left a screen reader nowhere).
function disable(id) {
  const focused = document.activeElement === $(id);
  $(id).disabled = true;
  if (focused) $("status").focus();
}

// Fill the decoder choice from GET /v1/decoders, keeping the one chosen if still listed
// (Save key pressed again put the server's default in its place, unsaid, and the next
// run used it); a failure (or no answer within POLL_TIMEOUT_MS: the choice stood empty
// without a word) says how to list them again (the page asks only at load and on Save
// key).
async function loadDecoders() {
  const select = $("decoder");
  const chosen = select.value;
  select.replaceChildren();
  try {
    const decoders = await readInTime("/v1/decoders", null, (reply) => reply.json());
    const kept = decoders.some((decoder) => decoder.name === chosen);
    for (const decoder of decoders) {
      const option = new Option(`${decoder.name} (${decoder.kind})`, decoder.name);
      option.title = decoder.description;
      option.selected = kept ? decoder.name === chosen : decoder.default;
      select.add(option);
    }
  } catch (error) {
    const again = error.status === 401 ? "" : "; then press Save key to list them again " +
      "(Reconstruct meanwhile uses the server's default decoder or the quality)";
    setStatus(`cannot list decoders: ${error.message}${again}`, "error");
  }
}

// The frame's parameters the page sends (under Sensor), by their form field names.
const SENSOR_PARAMETERS = ["encoding", "alpha", "bits"];

// The field id's value as sent: a number in plain digits ("1e1", which the browser takes
// as the number 10, was refused by the API as no integer for bits), else as given.
function fieldValue(id) {
  const input = $(id);
  return input.type === "number" ? String(input.valueAsNumber) : input.value;
}

// The sensor fields of the form; simulating: the simulate's own too (exposure, clipping).
function sensorFields(form, simulating) {
  for (const name of SENSOR_PARAMETERS) {
    if ($(name).value) form.append(name, fieldValue(name));
  }
  if (!simulating) return;
  if ($("overexposed").value) form.append("overexposed", fieldValue("overexposed"));
  if ($("clip-negative").checked) form.append("clip_negative", "true");
}

// The error for a simulate the API refused: for negative scene values, which box to tick.
function simulateRefused(error) {
  if (error.code !== "negative_irradiance") return error;
  $("clip-negative").focus();
  return new ApiError(`the scene holds negative values, as lossy EXR compression leaves ` +
    `(${error.message}); tick “clip negative values to 0” under Sensor to set them to 0 ` +
    "and press Reconstruct again", error.status, null, error.code);
}

// The choices of "Upload", by the kind of file each takes.
const KINDS = { frame: ["a", "wrapped frame"], hdr: ["an", "HDR image"] };

// The error for an upload the API cannot read as kind (415: an HDR image sent as a
// frame, or a frame to be simulated): the API's words name its CLI and routes; this adds
// the choice under Upload that takes a file of the other kind.
function wrongKind(error, kind) {
  if (error.status !== 415) return error;
  const [article, other] = KINDS[kind === "hdr" ? "frame" : "hdr"];
  return new ApiError(`${error.message}; if the file is ${article} ${other}, choose ` +
    `“${other}” under Upload and press Reconstruct again`, error.status, null, error.code);
}

// "a", "a and b", "a, b and c".
const listed = (names) => names.length < 2 ? names.join("") :
  `${names.slice(0, -1).join(", ")} and ${names.at(-1)}`;

// The error for a frame the API cannot decode without parameters it does not store (an
// npy frame), stores unreadable or stores out of range: the API's words name its CLI
// flags and form fields (its parameters); this adds where they go on this page. Not
// where one of them is not on the page (the size of raw codes, a stored read noise).
function sensorMissing(error) {
  const asked = error.parameters || [];
  if (!asked.length || !asked.every((name) => SENSOR_PARAMETERS.includes(name))) return error;
  const fields = listed(SENSOR_PARAMETERS.filter((name) => asked.includes(name)));
  return new ApiError(`${error.message}; on this page, fill in ${fields} under Sensor and ` +
    "press Reconstruct again", error.status, null, error.code, asked);
}

// The sensor's frame of an HDR image, as a TIFF: it holds grey and colour frames alike
// (a PNG frame is grey only, and every Radiance .hdr is colour). Notes how many negative
// scene values were set to 0 (X-Mcam-Clipped-Negative) when that was asked for.
async function simulateFrame(file, signal) {
  setStatus("simulating the sensor…");
  const form = new FormData();
  form.append("file", file);
  form.append("format", "tiff");
  sensorFields(form, true);
  const request = { method: "POST", body: form, signal };
  const reply = await api("/v1/simulate", request).catch((error) => {
    throw wrongKind(simulateRefused(error), "hdr");
  });
  if (form.has("clip_negative")) {
    const clipped = reply.headers.get("X-Mcam-Clipped-Negative");
    inputNotes = [`simulate: ${clipped} negative scene values set to 0 (clip negative values)`];
    showNotes();
  }
  return new File([await reply.blob()], "frame.tiff", { type: "image/tiff" });
}

// The decoder choice as a form field: [name, value] of the quality, else the decoder.
function decoderField() {
  return $("quality").value ? ["quality", $("quality").value] : ["decoder", $("decoder").value];
}

// A new Idempotency-Key: a random UUID (crypto.randomUUID exists only in a secure
// context, and the page may be served over plain HTTP to another host than localhost).
function newIdempotencyKey() {
  if (crypto.randomUUID) return crypto.randomUUID();
  return Array.from(crypto.getRandomValues(new Uint8Array(16)),
    (byte) => byte.toString(16).padStart(2, "0")).join("");
}

// Submit frame with decoder (decoderField, read when Reconstruct was pressed); an
// AbortError once signal aborts (Cancel). The upload carries a new Idempotency-Key, kept
// in watched, by which Cancel finds the job of an upload the server received whole
// before its answer came.
async function submitFrame(frame, simulated, decoder, signal) {
  setStatus("uploading the frame…");
  const form = new FormData();
  form.append("file", frame);
  if (!simulated) sensorFields(form, false);
  form.append(...decoder);
  watched.uploadKey = newIdempotencyKey();
  const headers = { "Idempotency-Key": watched.uploadKey };
  const request = { method: "POST", body: form, signal, headers };
  const reply = await api("/v1/reconstructions", request).catch((error) => {
    throw simulated ? error : sensorMissing(wrongKind(error, "frame"));
  });
  return (await reply.json()).id;
}

const percent = (share) => `${(100 * share).toFixed(1)}%`;

// One line per fact of how the job's frame was decoded (GET /v1/jobs/{id} "info"):
// each channel's routes, refinement, clipped blobs filled or latency budget, and a
// colour frame's join. None before the decode (a queued, running, cancelled or failed
// job's info is {}: it read "decoder: undefined").
function describeDecode(info) {
  if (!info?.decoder) return "";
  const lines = [`decoder: ${info.decoder}`];
  const channels = info.channels || (info.details ? [info.details] : []);
  channels.forEach((facts, index) => {
    const label = channels.length > 1 ? `${"RGB"[index] ?? index}: ` : "";
    if (facts.routes) {
      const routes = Object.entries(facts.routes)
        .map(([route, share]) => `${route} ${percent(share)}`).join(", ");
      lines.push(`${label}${routes}${facts.reason ? ` (${facts.reason})` : ""}`);
    }
    if (facts.refinement) {
      const { decoder, changed_fraction: changed } = facts.refinement;
      lines.push(`${label}refined by ${decoder}: ${percent(changed)} of pixels changed`);
    }
    if (facts.saturation?.filled_fraction) {
      const filled = percent(facts.saturation.filled_fraction);
      lines.push(`${label}clipped blobs set to the sensor's clip: ${filled} of pixels`);
    }
    if (facts.budget) {
      const { budget_ms: budget, chosen, measured_ms: took } = facts.budget;
      lines.push(`${label}latency budget ${budget} ms: ${chosen}, took ${took} ms`);
    }
  });
  const colour = info.colour;
  if (colour) {
    const changed = colour.reason ? "" : percent(colour.changed_fraction);
    lines.push(colour.reason ?? `colour: channels made consistent, ${changed} of pixel-channels changed`);
  }
  return lines.join("\n");
}

// The notes on this run's input, and the job's warnings (a file read as another format
// than its name says: the API tells it in the job's "warnings").
function showNotes(warnings = []) {
  const lines = [...inputNotes, ...warnings.map((warning) => `warning: ${warning}`)];
  $("notes").textContent = lines.join("\n");
  $("notes").className = warnings.length ? "warning" : "";
}

function showJob(job) {
  showNotes(job.warnings);
  $("progress").value = job.progress;
  const stages = Object.entries(job.timings_ns || {})
    .map(([stage, ns]) => `${stage}: ${(ns / 1e6).toFixed(1)} ms`);
  $("timings").textContent = stages.join("\n");
  $("routing").textContent = describeDecode(job.info);
  const error = job.error ? ` (${job.error.code}: ${job.error.message})` : "";
  setStatus(`job ${job.id}: ${job.state}${error}`, job.state === "failed" ? "error" : "");
}

// Keep the notes on job id's input for the tab, or take them back after a reload (they
// are the page's, not the job's: a reload lost "simulate: N negative scene values set
// to 0" while the job, and its scene so clipped, ran on).
function keepNotes(id) {
  const key = `mcam-notes-${id}`;
  if (inputNotes.length) sessionStorage.setItem(key, JSON.stringify(inputNotes));
  else inputNotes = JSON.parse(sessionStorage.getItem(key) ?? "[]");
}

function clearJob() {
  inputNotes = [];
  showNotes();
  $("progress").value = 0;
  $("timings").textContent = "";
  $("routing").textContent = "";
}

// The reply of path to method as read (read: its json or blob). One that stalls (no
// answer, or no byte of its body, within idleMs) is given up as an unreachable server's
// error (retried by the polls), one asked for until signal (if any) aborted is an
// AbortError. (A timer, not AbortSignal.any, which Firefox 115 ESR lacks.)
async function readInTime(path, signal, read, { idleMs = POLL_TIMEOUT_MS, method = "GET" } = {}) {
  const asked = new AbortController();
  const abort = () => asked.abort();
  signal?.addEventListener("abort", abort, { once: true });
  let timer = setTimeout(abort, idleMs);
  const restart = () => { clearTimeout(timer); timer = setTimeout(abort, idleMs); };
  try {
    const reply = await api(path, { method, signal: asked.signal });
    return await read(await whole(reply, restart));
  } catch (error) {
    throw asked.signal.aborted && !signal?.aborted ? noAnswer(idleMs) : error;
  } finally {
    clearTimeout(timer);
    signal?.removeEventListener("abort", abort);
  }
}

// The error of a request of which no byte came within ms.
const noAnswer = (ms) => new ApiError(`no answer from the server within ${ms / 1000} s ` +
  "(the connection died, or the server stopped); check that mcam serve is running");

// reply with its body read whole, calling restart() as each piece of it comes.
async function whole(reply, restart) {
  restart();
  if (!reply.body) return reply;
  const pieces = [];
  const reader = reply.body.getReader();
  for (let piece = await reader.read(); !piece.done; piece = await reader.read()) {
    pieces.push(piece.value);
    restart();
  }
  const { status, statusText, headers } = reply;
  return new Response(new Blob(pieces), { status, statusText, headers });
}

// The job's record (see readInTime).
const fetchJob = (id, signal) => readInTime(`/v1/jobs/${id}`, signal, (reply) => reply.json());

// Poll the job until it finished, at growing intervals. A failed poll (server down, 503,
// 429) keeps the job on screen and is retried (after Retry-After if given); a 404 or 410
// means the job is gone. Returns the finished job, or null once signal aborts (Cancel).
async function waitForJob(id, signal) {
  let pollMs = POLL_FIRST_MS;
  let failures = 0;
  while (!signal.aborted) {
    let delayMs;
    try {
      const job = await fetchJob(id, signal);
      showJob(job);
      if (FINISHED.includes(job.state)) return job;
      failures = 0;
      delayMs = pollMs;
      pollMs = Math.min(pollMs * 1.5, POLL_MAX_MS);
    } catch (error) {
      if (signal.aborted) break;
      if (isGone(error)) {
        throw new ApiError(`job ${id} no longer exists on the server (${error.message}); ` +
          "submit the frame again");
      }
      if (isFinal(error)) throw new ApiError(`job ${id}: ${error.message}`, error.status);
      if (!(error instanceof ApiError)) throw error;
      failures += 1;
      delayMs = retryDelayMs(error, failures);
      setStatus(`job ${id}: ${retryNote(error, delayMs)} (Cancel stops waiting)`, "warning");
    }
    await sleep(delayMs, signal);
  }
  return null;
}

// The job's result for query as read (read: its json or blob; none within
// RESULT_TIMEOUT_MS: given up, see readInTime); one the server was too busy to make is
// asked for again after its Retry-After (RESULT_TRIES in all), told to onBusy (if any)
// as (error, wait in ms). Once signal (if any) aborts (Cancel, another job or exposure
// shown), it asks no more: AbortError.
async function result(job, query, read, signal = null, onBusy = null) {
  const path = `/v1/jobs/${job}/result?${query}`;
  for (let tries = 1; ; tries += 1) {
    try {
      return await readInTime(path, signal, read, { idleMs: RESULT_TIMEOUT_MS });
    } catch (error) {
      if (tries >= RESULT_TRIES || !BUSY.includes(error.status)) throw error;
      const delayMs = retryDelayMs(error, tries);
      onBusy?.(error, delayMs);
      await sleep(delayMs, signal);
      signal?.throwIfAborted();
    }
  }
}

const resultBlob = (job, query, signal = null, onBusy = null) =>
  result(job, query, (reply) => reply.blob(), signal, onBusy);

// The onBusy of result for the succeeded job: the status says its result is asked for
// again (the panels stayed empty beside "succeeded", up to four Retry-Afters: minutes on
// a 429) until resultCame.
function resultsBusy(job) {
  return (error, delayMs) => {
    setStatus(`job ${job}: succeeded; its results: ${retryNote(error, delayMs)}`, "warning");
    resultsBusyShown = true;
  };
}

// A result of job came: a note that one was asked for again gives way to "succeeded".
function resultCame(job) {
  if (resultsBusyShown) setStatus(`job ${job}: succeeded`);
}

// Show blob in the image element id (null: empty it).
function setImage(id, blob) {
  const img = $(id);
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  if (blob) img.src = URL.createObjectURL(blob);
  else img.removeAttribute("src");
}

const hdrQuery = () => `format=png&exposure=${exposure()}`;

function exposure() {
  return Number($("exposure").value);
}

function drawHistogram() {
  const canvas = $("histogram");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!histogram || histogram.counts.length === 0) return;
  const { counts, log10_edges: edges } = histogram;
  const low = edges[0];
  const span = edges[edges.length - 1] - low || 1;
  const x = (value) => ((value - low) / span) * canvas.width;
  // The luminance range the preview shows: 2^-EV * [sRGB black step, 1].
  const top = -exposure() * Math.log10(2);
  ctx.fillStyle = "#fde72533";
  ctx.fillRect(x(top - 2.5), 0, x(top) - x(top - 2.5), canvas.height);
  const peak = Math.max(...counts);
  ctx.fillStyle = "#3b528b";
  counts.forEach((count, i) => {
    const height = (count / peak) * (canvas.height - 18);
    ctx.fillRect(x(edges[i]), canvas.height - 14 - height, Math.max(x(edges[i + 1]) - x(edges[i]) - 1, 1), height);
  });
  ctx.fillStyle = "#333";
  ctx.font = "11px sans-serif";
  ctx.fillText(`log10 luminance ${low.toFixed(2)}`, 2, canvas.height - 2);
  const right = `${edges[edges.length - 1].toFixed(2)}`;
  ctx.fillText(right, canvas.width - ctx.measureText(right).width - 2, canvas.height - 2);
}

// Empty the result panels: nothing of an earlier job stays beside a new one.
function clearResult() {
  shownJob = null;
  hdrStop.abort();
  clearTimeout(exposureTimer);
  for (const id of ["img-codes", "img-winding", "img-hdr"]) setImage(id, null);
  histogram = null;
  drawHistogram();
  disable("download");
}

// Fetch every panel of the succeeded job, then show them together; none once signal
// aborts. While the server is too busy to make them the status says so (resultsBusy),
// and the first that cannot be fetched stops the others (whose notes would hide why).
async function showResult(job, signal) {
  const ev = exposure();
  const stop = new AbortController();
  if (signal.aborted) stop.abort();
  signal.addEventListener("abort", () => stop.abort(), { once: true });
  const panels = stop.signal;
  const busy = resultsBusy(job);
  const [codes, winding, hdr, counts] = await Promise.all([
    resultBlob(job, "part=codes&format=png", panels, busy),
    resultBlob(job, "part=winding&format=png", panels, busy),
    resultBlob(job, hdrQuery(), panels, busy),
    result(job, "part=histogram", (reply) => reply.json(), panels, busy),
  ]).catch((error) => {
    stop.abort();
    throw error;
  });
  resultCame(job);
  setImage("img-codes", codes);
  setImage("img-winding", winding);
  setImage("img-hdr", hdr);
  histogram = counts;
  drawHistogram();
  shownJob = job;
  $("download").disabled = false;
  if (exposure() !== ev) refreshHdr();
}

// Tonemap the shown job's HDR again at the slider's exposure. Only the latest request
// goes on: a later one or other panels abort it (an earlier reply arriving late would
// show another exposure, and its retries would go on for a job no longer shown).
let hdrStop = new AbortController();
async function refreshHdr() {
  const job = shownJob;
  if (!job) return;
  hdrStop.abort();
  const { signal } = (hdrStop = new AbortController());
  try {
    const blob = await resultBlob(job, hdrQuery(), signal, resultsBusy(job));
    if (signal.aborted) return;
    setImage("img-hdr", blob);
    resultCame(job);
  } catch (error) {
    if (signal.aborted) return;
    setStatus(`cannot tonemap job ${job} again: ${error.message}; move the exposure ` +
      "slider to try again", "error");
  }
}

// The page's address names the job in flight or shown (#job=<id>), so that a reload, or
// leaving the page and coming back, follows it again (it was forgotten: "No job yet.").
const JOB_HASH = /^#job=([0-9a-f]{32})$/;

// Put job id (null: none) in the page's address, adding no history entry.
function setJobHash(id) {
  history.replaceState(null, "", id ? `#job=${id}` : location.pathname + location.search);
}

// Follow the job whose id start(signal) resolves to (a submit, or the address's job):
// watch it until it finished, then show its results. Cancel stops the upload too
// (start's AbortError; a large file's upload could not be stopped).
async function follow(start) {
  disable("run");
  clearJob();
  clearResult();
  setJobHash(null);
  const run = { id: null, stop: new AbortController(), uploadKey: null, cancelling: null };
  watched = run;
  const { signal } = run.stop;
  $("cancel").disabled = false;
  try {
    const id = await start(signal);
    watched.id = id;
    setJobHash(id);
    keepNotes(id);
    const job = await waitForJob(id, signal);
    if (job?.state === "succeeded") {
      await showResult(id, signal).catch(resultsUnreachable(id));
    }
  } catch (error) {
    if (error.name !== "AbortError") setStatus(error.message, "error");
  } finally {
    await run.cancelling; // a Cancel still finding or cancelling the upload's job
    watched = null;
    disable("cancel");
    $("run").disabled = false;
  }
}

// The job id the page's address names (null: none).
const addressJob = () => JOB_HASH.exec(location.hash)?.[1] ?? null;

// The address's job unless it is watched or shown already (null: none such).
function unfollowedAddressJob() {
  const id = addressJob();
  return id && watched?.id !== id && shownJob !== id ? id : null;
}

// Follow the job the page's address names, unless it is watched or shown already: at
// load, and once a key is saved (opened without one, the page asked for the key and
// saving it never followed the job).
function followAddressJob() {
  const id = unfollowedAddressJob();
  if (id) follow(async () => id);
}

// An address naming another job, entered or opened while the page is open (only its
// #job= changed, so the page was not loaded again: it went on showing the job it had
// under the other's address): the page is loaded afresh, which follows that job.
function onAddressChange() {
  if (unfollowedAddressJob()) location.reload();
}

// Say so if the address's #job= holds no job id (cut short or changed when copied): the
// page read "No job yet." as if it named none.
function refuseAddressWithoutJob() {
  if (!location.hash.startsWith("#job=") || addressJob()) return;
  setStatus(`the page's address names no job: “${location.hash.slice(5)}” is not a job ` +
    "id (32 characters 0-9 and a-f); copy the job's whole address again", "error");
}

// Submit file (an HDR image simulated first, as Upload says); resolves to the job's id,
// or an AbortError once signal aborts (Cancel). The decoder is read at once: one chosen
// while the simulate runs is for the next run.
async function submitFile(file, signal) {
  const simulated = document.querySelector("input[name=kind]:checked").value === "hdr";
  const decoder = decoderField();
  const frame = simulated ? await simulateFrame(file, signal) : file;
  return submitFrame(frame, simulated, decoder, signal);
}

function run(event) {
  event.preventDefault();
  const file = $("file").files[0];
  if (!file) return setStatus("choose a file first", "error");
  follow((signal) => submitFile(file, signal));
}

// An error handler for the results of job id that could not be fetched: what to do
// says how to fetch them again (the page's address names the job, so a reload follows
// it again), or, once the server no longer has them, to run it again (it said so
// whatever went wrong, and a new run lost the job already done).
function resultsUnreachable(id) {
  return (error) => {
    if (error.name === "AbortError") return; // stopped by Cancel, which said so
    const again = isGone(error) ? "press Reconstruct to run it again"
      : `reload the page (its address names job ${id}) to fetch them again`;
    throw new ApiError(`job ${id} succeeded, but its results could not be fetched ` +
      `(${error.message}); ${again}`);
  };
}

// Cancel the upload in flight (cancelUpload), or the job in flight (cancelJob). The
// run ends (Reconstruct is enabled again) once the Cancel has.
function cancel() {
  const run = watched;
  disable("cancel");
  run.cancelling = run.id ? cancelJob(run.id, run.stop) : cancelUpload(run);
}

// Cancel job id (DELETE /v1/jobs/{id}) and stop waiting for it and its results (stop).
// One that finished meanwhile (409) is not fetched further either: the page shows its
// record (why it failed) and says so. If the server cannot be told (or does not answer
// within POLL_TIMEOUT_MS: a Cancel on a dead connection did nothing, and the page waited
// on), the page stops waiting all the same and says so.
async function cancelJob(id, stop) {
  try {
    const job = await readInTime(`/v1/jobs/${id}`, null, (reply) => reply.json(),
      { method: "DELETE" });
    stop.abort();
    showJob(job);
  } catch (error) {
    stop.abort();
    if (error.status === 409) return finishedBeforeCancel(id, error);
    setStatus(`job ${id}: stopped waiting, but the server could not cancel it ` +
      `(${error.message}); it may still run: reload the page (its address names it) to ` +
      "follow it again", "error");
  }
}

const UPLOAD_CANCELLED = "upload cancelled before the server answered: no job was made; " +
  "press Reconstruct to upload the file again";

// Stop the upload (or the simulate before it) in flight of run: its server had not
// answered. An upload it had received whole may have made its job all the same (which
// ran on, followed by no page): that job is found by the upload's Idempotency-Key and
// cancelled, as the run's job (its id in the page's address).
async function cancelUpload(run) {
  run.stop.abort();
  if (!run.uploadKey) return setStatus(UPLOAD_CANCELLED);
  setStatus("cancelling: asking the server whether the upload made a job…");
  let job;
  try {
    job = await uploadedJob(run.uploadKey);
  } catch (error) {
    return setStatus("upload cancelled, but the server could not say whether it made a " +
      `job (${error.message}); if it did, the job runs on, followed by no page: ` +
      `GET /v1/jobs?idempotency_key=${run.uploadKey} finds it, to follow or cancel it`,
      "error");
  }
  if (!job) return setStatus(UPLOAD_CANCELLED);
  run.id = job.id;
  setJobHash(job.id);
  await cancelJob(job.id, run.stop);
}

// The job the upload sent with Idempotency-Key key made (null: none; GET
// /v1/jobs?idempotency_key=), asked again while the server is still handling the upload
// (409) or cannot be reached, for up to UPLOAD_LOOKUP_MS.
async function uploadedJob(key) {
  const path = `/v1/jobs?idempotency_key=${encodeURIComponent(key)}`;
  const deadline = Date.now() + UPLOAD_LOOKUP_MS;
  for (let failures = 1; ; failures += 1) {
    try {
      return await readInTime(path, null, (reply) => reply.json());
    } catch (error) {
      if (isGone(error)) return null;
      const again = error instanceof ApiError && (error.status === 409 || !isFinal(error));
      if (!again || Date.now() > deadline) throw error;
      await sleep(retryDelayMs(error, failures));
    }
  }
}

// Job id had finished when Cancel reached the server (refused: error). A failed one is
// shown as its record says (why it failed: it has no results to stop fetching); for
// one that succeeded, or whose record cannot be read, the page says that it stopped
// fetching its results. Nothing is shown once another job is watched.
async function finishedBeforeCancel(id, error) {
  let job = null;
  try {
    job = await fetchJob(id, null);
  } catch {
    // the record is out of reach: the refusal's own message says what happened
  }
  if (watched && watched.id !== id) return;
  if (job?.state === "failed") return showJob(job);
  setStatus(`job ${id} had finished before Cancel (${error.message}): stopped fetching ` +
    "its results; press Reconstruct to run it again", "warning");
}

// Name the slider's exposure in the HDR panel's caption.
function showExposure() {
  $("ev-value").textContent = exposure();
}

function onExposure() {
  showExposure();
  drawHistogram();
  clearTimeout(exposureTimer);
  if (shownJob) exposureTimer = setTimeout(refreshHdr, 120);
}

// Save the shown job's EXR as <job id>.exr (the id taken at the click: a Run pressed
// while it downloads clears shownJob, and the file was saved as null.exr). While the
// server is too busy to give it, the status says it is asked for again (resultsBusy: a
// click did nothing to be seen for up to four Retry-Afters). One that failed says it was
// the download (the bare "cannot reach the server" read as the job's failure).
async function download() {
  const job = shownJob;
  try {
    const blob = await resultBlob(job, "part=image&format=exr", null, resultsBusy(job));
    resultCame(job);
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = `${job}.exr`;
    link.click();
    URL.revokeObjectURL(link.href);
  } catch (error) {
    const again = isGone(error) ? "Reconstruct to run it again" : "Download EXR to try again";
    setStatus(`cannot download the EXR of job ${job}: ${error.message}; press ${again}`,
      "error");
  }
}

$("api-key").value = apiKey();
// Back to the page, the browser restores the slider where it was, once the page loaded:
// the caption named the HTML's 0 EV beside previews made at the restored exposure.
window.addEventListener("pageshow", showExposure);
window.addEventListener("hashchange", onAddressChange);
$("key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const key = $("api-key").value.trim();
  if (!KEY_PATTERN.test(key)) {
    return setStatus("not saved: an API key is letters, digits and punctuation, without " +
      "spaces or typographic dashes; paste it again as mcam serve printed it", "error");
  }
  localStorage.setItem(KEY_STORAGE, key);
  setStatus("API key saved.");
  loadDecoders();
  followAddressJob();
});
$("job-form").addEventListener("submit", run);
$("exposure").addEventListener("input", onExposure);
$("download").addEventListener("click", download);
$("cancel").addEventListener("click", cancel);
if (apiKey()) {
  loadDecoders();
  followAddressJob();
} else {
  const named = addressJob();
  setStatus("Enter the API key (printed by mcam serve on first start) and save it" +
    (named ? `: then job ${named} is followed.` : "."));
}
refuseAddressWithoutJob();
