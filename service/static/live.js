// Live view of camera devices: health counters and the newest reconstructed frame, polled
// once a second (EventSource cannot send the API key header, so the page polls).
"use strict";

const LIVE_POLL_MS = 1000;
let liveTimer = null;
let liveUrl = null;

async function listDevices() {
  const select = document.getElementById("live-device");
  select.replaceChildren(new Option("(choose a device)", ""));
  try {
    const { devices } = await (await api("/v1/devices")).json();
    for (const device of devices) select.add(new Option(`${device.id} (${device.state})`, device.id));
    document.getElementById("live-status").textContent = `${devices.length} device(s)`;
  } catch (error) {
    document.getElementById("live-status").textContent = `cannot list devices: ${error.message}`;
  }
}

async function pollDevice(id) {
  const status = document.getElementById("live-status");
  try {
    const health = await (await api(`/v1/devices/${encodeURIComponent(id)}`)).json();
    const dropped = Object.values(health.dropped).reduce((a, b) => a + b, 0);
    status.textContent = `${health.state}: ${health.frames_ok} frames, ${health.fps} fps, ` +
      `${dropped} dropped, ${health.sequence_gaps} gaps, ${health.reconnects} reconnects`;
    if (!health.latest_result) return;
    const ev = document.getElementById("exposure").value;
    const blob = await (await api(`/v1/devices/${encodeURIComponent(id)}/frames/latest` +
      `?format=png&exposure=${ev}`)).blob();
    if (liveUrl) URL.revokeObjectURL(liveUrl);
    liveUrl = URL.createObjectURL(blob);
    document.getElementById("live-frame").src = liveUrl;
  } catch (error) {
    status.textContent = `device ${id}: ${error.message}`;
  }
}

document.getElementById("live-refresh").addEventListener("click", listDevices);
document.getElementById("live-device").addEventListener("change", (event) => {
  clearInterval(liveTimer);
  const id = event.target.value;
  if (id) liveTimer = setInterval(() => pollDevice(id), LIVE_POLL_MS);
});
