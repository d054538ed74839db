// MantissaCam web viewer: upload, (simulate,) reconstruct, watch the job, inspect the result.
// Plain browser JavaScript, no build step. Every request carries the API key (localStorage).
"use strict";

const $ = (id) => document.getElementById(id);
const KEY_STORAGE = "mcam-api-key";
const POLL_MS = 300;
let currentJob = null;
let histogram = null;
let exposureTimer = null;

class ApiError extends Error {}

function apiKey() {
  return localStorage.getItem(KEY_STORAGE) || "";
}

async function api(path, options = {}) {
  const headers = { Authorization: `Bearer ${apiKey()}`, ...(options.headers || {}) };
  const reply = await fetch(path, { ...options, headers });
  if (!reply.ok) {
    let message = `${reply.status} ${reply.statusText}`;
    try {
      const body = await reply.json();
      message = `${body.code}: ${body.message}`;
    } catch (_) { /* not JSON: keep the status line */ }
    throw new ApiError(message);
  }
  return reply;
}

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").classList.toggle("error", isError);
}

async function loadDecoders() {
  const select = $("decoder");
  select.replaceChildren();
  try {
    const decoders = await (await api("/v1/decoders")).json();
    for (const decoder of decoders) {
      const option = new Option(`${decoder.name} (${decoder.kind})`, decoder.name);
      option.title = decoder.description;
      option.selected = decoder.default;
      select.add(option);
    }
  } catch (error) {
    setStatus(`cannot list decoders: ${error.message}`, true);
  }
}

function sensorFields(form, includeExposure) {
  for (const name of ["encoding", "alpha", "bits"]) {
    if ($(name).value) form.append(name, $(name).value);
  }
  if (includeExposure && $("overexposed").value) form.append("overexposed", $("overexposed").value);
}

async function simulateFrame(file) {
  setStatus("simulating the sensor…");
  const form = new FormData();
  form.append("file", file);
  sensorFields(form, true);
  const reply = await api("/v1/simulate", { method: "POST", body: form });
  return new File([await reply.blob()], "frame.png", { type: "image/png" });
}

async function submitFrame(frame, simulated) {
  const form = new FormData();
  form.append("file", frame);
  if (!simulated) sensorFields(form, false);
  if ($("quality").value) form.append("quality", $("quality").value);
  else form.append("decoder", $("decoder").value);
  const reply = await api("/v1/reconstructions", { method: "POST", body: form });
  return (await reply.json()).id;
}

const percent = (share) => `${(100 * share).toFixed(1)}%`;

// One line per fact of how the job's frame was decoded (GET /v1/jobs/{id} "info"):
// each channel's routes, refinement, clipped blobs filled or latency budget, and a
// colour frame's join.
function describeDecode(info) {
  if (!info) return "";
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

function showJob(job) {
  $("progress").value = job.progress;
  const stages = Object.entries(job.timings_ns || {})
    .map(([stage, ns]) => `${stage}: ${(ns / 1e6).toFixed(1)} ms`);
  $("timings").textContent = stages.join("\n");
  $("routing").textContent = describeDecode(job.info);
  const error = job.error ? ` (${job.error.code}: ${job.error.message})` : "";
  setStatus(`job ${job.id}: ${job.state}${error}`, job.state === "failed");
}

async function waitForJob(id) {
  for (;;) {
    const job = await (await api(`/v1/jobs/${id}`)).json();
    showJob(job);
    if (["succeeded", "failed", "cancelled"].includes(job.state)) return job;
    await new Promise((resolve) => setTimeout(resolve, POLL_MS));
  }
}

async function showImage(id, query) {
  const blob = await (await api(`/v1/jobs/${currentJob}/result?${query}`)).blob();
  const img = $(id);
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  img.src = URL.createObjectURL(blob);
}

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

async function showResult() {
  await Promise.all([
    showImage("img-codes", "part=codes&format=png"),
    showImage("img-winding", "part=winding&format=png"),
    showImage("img-hdr", `format=png&exposure=${exposure()}`),
  ]);
  histogram = await (await api(`/v1/jobs/${currentJob}/result?part=histogram`)).json();
  drawHistogram();
  $("download").disabled = false;
}

async function run(event) {
  event.preventDefault();
  const file = $("file").files[0];
  if (!file) return setStatus("choose a file first", true);
  $("run").disabled = true;
  $("download").disabled = true;
  try {
    const simulated = document.querySelector("input[name=kind]:checked").value === "hdr";
    const frame = simulated ? await simulateFrame(file) : file;
    currentJob = await submitFrame(frame, simulated);
    const job = await waitForJob(currentJob);
    if (job.state === "succeeded") await showResult();
  } catch (error) {
    setStatus(error.message, true);
  } finally {
    $("run").disabled = false;
  }
}

function onExposure() {
  $("ev-value").textContent = exposure();
  drawHistogram();
  clearTimeout(exposureTimer);
  if (!currentJob) return;
  exposureTimer = setTimeout(() => {
    showImage("img-hdr", `format=png&exposure=${exposure()}`).catch((e) => setStatus(e.message, true));
  }, 120);
}

async function download() {
  try {
    const blob = await (await api(`/v1/jobs/${currentJob}/result`)).blob();
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = `${currentJob}.exr`;
    link.click();
    URL.revokeObjectURL(link.href);
  } catch (error) {
    setStatus(error.message, true);
  }
}

$("api-key").value = apiKey();
$("key-form").addEventListener("submit", (event) => {
  event.preventDefault();
  localStorage.setItem(KEY_STORAGE, $("api-key").value.trim());
  setStatus("API key saved.");
  loadDecoders();
});
$("job-form").addEventListener("submit", run);
$("exposure").addEventListener("input", onExposure);
$("download").addEventListener("click", download);
if (apiKey()) loadDecoders();
else setStatus("Enter the API key (printed by mcam serve on first start) and save it.");
