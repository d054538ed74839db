// Live view of camera devices: health counters and the newest reconstructed frame, polled
// once a second (EventSource cannot send the API key header, so the page polls). The frame
// is fetched only when a newer one came or the exposure changed. A failed poll is retried
// after a growing wait (Retry-After on a 429 or 503); a device the server no longer knows
// ends the watch. A poll not answered within POLL_TIMEOUT_MS (a connection that died
// without closing) is retried as a lost connection: it was waited for without end, and
// the view stood still however the device came back. Uses ApiError, apiKey, readInTime,
// sleep, retryDelayMs, retryNote, isGone, isFinal and setImage from app.js.
"use strict";

const LIVE_POLL_MS = 1000;
let liveWatch = null; // AbortController of the device being watched

// Show the live status line from its parts (at most 5), said and quiet by turns: the
// said ones are live regions (index.html), the quiet ones, which change at every poll
// (the frame counters, a silent daemon's age), are in none. A part is written only when
// its text changed. The whole line was one live region, written every second: a screen
// reader read it out again every second.
function liveStatus(...parts) {
  const line = document.getElementById("live-status").children;
  [...line].forEach((part, index) => {
    const text = parts[index] ?? "";
    if (part.textContent !== text) part.textContent = text;
  });
}

// Stop watching the device, and empty its frame and health: nothing of one device stays
// on screen beside another's, or once none is chosen.
function stopLiveWatch() {
  liveWatch?.abort();
  liveWatch = null;
  setImage("live-frame", null);
  liveStatus("");
}

// The device chosen in this tab is kept in sessionStorage: a reload (or a List devices)
// lost it, and the live view stood empty until the device was chosen again.
const DEVICE_STORAGE = "mcam-live-device";

// List the devices; the one chosen before, if listed, is chosen and watched again. A
// list not answered within POLL_TIMEOUT_MS (a connection that died without closing: the
// list stood empty without a word) is given up, and a failure says how to ask again.
async function listDevices() {
  stopLiveWatch();
  const select = document.getElementById("live-device");
  select.replaceChildren(new Option("(choose a device)", ""));
  try {
    const { devices } = await readInTime("/v1/devices", null, (reply) => reply.json());
    for (const device of devices) select.add(new Option(`${device.id} (${deviceState(device)})`, device.id));
    liveStatus(`${devices.length} device(s)`);
  } catch (error) {
    const again = error.status === 401 ? "" : "; press List devices to try again";
    liveStatus(`cannot list devices: ${error.message}${again}`);
    return;
  }
  const chosen = sessionStorage.getItem(DEVICE_STORAGE);
  if (chosen && [...select.options].some((option) => option.value === chosen)) {
    select.value = chosen;
    startLiveWatch(chosen);
  }
}

// A device's state; none before its daemon's first health report (the daemon's first
// frame can register the device just before it; the API then shows no health fields).
const deviceState = (health) => health.state ?? "no health report yet";

// Why the device sends no frames, and what to do, as liveStatus's parts (from a said
// one): its daemon went silent (the API's state "silent": no health report for age_s
// seconds), its daemon crashed (the state "crashed", the error in crash), or its port
// does not open (the daemon's port_error: a wrong --port, an unplugged camera, another
// daemon on it); else none.
function healthTrouble(health) {
  if (health.state === "silent") {
    return ["; its daemon has not reported for ", `${Math.round(health.age_s)} s`,
      " (stopped, killed, or cut off from Redis): check that mcam device runs"];
  }
  if (health.state === "crashed") {
    return [`; its daemon stopped on an unexpected error (${health.crash}): restart mcam ` +
      "device, and report the error with the traceback in its log"];
  }
  return health.port_error ? [`; its port does not open: ${health.port_error}`] : [];
}

// The device's health in one line, with what keeps it from sending frames, as
// liveStatus's parts: its state, its counters, and its trouble.
function describeHealth(health) {
  if (!health.state) return [`${deviceState(health)} from the device's daemon`];
  const dropped = Object.values(health.dropped).reduce((a, b) => a + b, 0);
  const counters = `: ${health.frames_ok} frames, ${health.fps} fps, ${dropped} dropped, ` +
    `${health.sequence_gaps} gaps, ${health.reconnects} reconnects`;
  return [health.state, counters, ...healthTrouble(health)];
}

// The device's health; an error marked deviceGone if the server no longer knows it.
async function deviceHealth(path, signal) {
  try {
    return await readInTime(path, signal, (reply) => reply.json());
  } catch (error) {
    error.deviceGone = isGone(error);
    throw error;
  }
}

// One poll: show the health and, if it changed, the newest frame. Returns what the frame
// on screen shows (newest result and exposure) for the next poll to compare with.
async function pollDevice(id, shown, signal) {
  const path = `/v1/devices/${encodeURIComponent(id)}`;
  const health = await deviceHealth(path, signal);
  liveStatus(...describeHealth(health));
  const ev = document.getElementById("exposure").value;
  const wanted = `${health.latest_result} at ${ev} EV`;
  if (!health.latest_result || wanted === shown) return shown;
  const frame = `${path}/frames/latest?format=png&exposure=${ev}`;
  const blob = await readInTime(frame, signal, (reply) => reply.blob());
  signal.throwIfAborted();
  setImage("live-frame", blob);
  return wanted;
}

async function watchDevice(id, signal) {
  let shown = "";
  let failures = 0;
  while (!signal.aborted) {
    let delayMs = LIVE_POLL_MS;
    try {
      shown = await pollDevice(id, shown, signal);
      failures = 0;
    } catch (error) {
      if (signal.aborted) return;
      if (error.deviceGone) {
        liveStatus(`device ${id} is no longer known to the server (${error.message}); ` +
          "press List devices");
        return;
      }
      if (!(error instanceof ApiError) || isFinal(error)) {
        liveStatus(`device ${id}: ${error.message}; the watch stopped`);
        return;
      }
      failures += 1;
      delayMs = Math.max(retryDelayMs(error, failures), LIVE_POLL_MS);
      liveStatus(`device ${id}: ${retryNote(error, delayMs)}`);
    }
    await sleep(delayMs, signal);
  }
}

// Watch device id (none: ""), in place of the one watched. liveWatch is null again once
// the watch ended by itself.
function startLiveWatch(id) {
  stopLiveWatch();
  if (!id) return;
  const watch = new AbortController();
  liveWatch = watch;
  watchDevice(id, watch.signal).finally(() => {
    if (liveWatch === watch) liveWatch = null;
  });
}

// Once a key is saved, list the devices again (watching the chosen one again) if they
// were listed and no watch runs: a key refused 401 or 403 stopped the watch or the list,
// and saving the right key, as the status said to, left them so (choosing the same
// device again is no change of the choice).
function resumeLiveWatch() {
  if (document.getElementById("live-device").options.length && !liveWatch) listDevices();
}

// Watch the device chosen, and keep the choice for a reload.
function onDeviceChosen(event) {
  const id = event.target.value;
  if (id) sessionStorage.setItem(DEVICE_STORAGE, id);
  else sessionStorage.removeItem(DEVICE_STORAGE);
  startLiveWatch(id);
}

document.getElementById("live-refresh").addEventListener("click", listDevices);
document.getElementById("live-device").addEventListener("change", onDeviceChosen);
document.getElementById("key-form").addEventListener("submit", resumeLiveWatch);
if (apiKey() && sessionStorage.getItem(DEVICE_STORAGE)) listDevices();
