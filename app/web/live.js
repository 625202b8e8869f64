// Live view: the site's position stream over a WebSocket, markers on the plan for the
// devices on the shown floor, a device list with last-seen ages, and zone events.

import { deviceColour, shapeIcon } from "./devices.js";
import { DeviceMarker } from "./plan.js";

const TRAIL_LENGTH = 20;
const STALE_AFTER_MS = 30_000;
const MAX_EVENTS = 200;
const BACKOFF_FIRST_MS = 500;
const BACKOFF_MAX_MS = 15_000;
const POLICY_VIOLATION = 1008; // the server's answer to a key that may not read the site

export class LiveView {
  constructor(api, plan, els, { onDevice }) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.onDevice = onDevice;
    this.siteId = null;
    this.floorId = null;
    this.socket = null;
    this.retryTimer = null;
    this.countdown = null;
    this.attempt = 0;
    this.devices = new Map();
    setInterval(() => this.#renderAges(), 1000);
  }

  /** Follow a site's stream (null to stop), forgetting the previous site's devices. */
  setSite(siteId) {
    if (siteId === this.siteId) return;
    this.#disconnect();
    this.siteId = siteId;
    for (const device of this.devices.values()) device.marker?.remove();
    this.devices.clear();
    this.els.devices.replaceChildren();
    this.els.events.replaceChildren();
    this.els.noEvents.hidden = false;
    this.#renderCount();
    if (siteId) this.#connect();
  }

  /** Draw only the devices whose latest position is on this floor. */
  setFloor(floorId) {
    this.floorId = floorId;
    for (const [id, device] of this.devices) {
      this.#draw(id, device);
      this.#renderRow(id, device);
    }
  }

  setVisible(visible) {
    this.plan.setVisible("live", visible);
  }

  #connect() {
    this.#cancelRetry();
    this.#state("connecting", "Connecting…");
    const socket = new WebSocket(this.api.positionsUrl(this.siteId));
    this.socket = socket;
    socket.addEventListener("open", () => {
      this.attempt = 0;
      this.#state("live", "Live");
    });
    socket.addEventListener("message", (event) => this.#receive(JSON.parse(event.data)));
    socket.addEventListener("close", (event) => {
      if (this.socket !== socket) return;
      this.socket = null;
      if (event.code === POLICY_VIOLATION) {
        this.#state("closed", `Refused: ${event.reason || "key may not read this site"}`);
        return;
      }
      this.#retry();
    });
  }

  #retry() {
    // delay = min(max, first · 2^attempt), with ±20 % jitter so dashboards do not reconnect in step
    const base = Math.min(BACKOFF_MAX_MS, BACKOFF_FIRST_MS * 2 ** this.attempt);
    const delay = base * (0.8 + 0.4 * Math.random());
    this.attempt += 1;
    const due = Date.now() + delay;
    const countdown = () => {
      const seconds = Math.max(0, Math.ceil((due - Date.now()) / 1000));
      this.#state("retrying", `Reconnecting in ${seconds} s`);
    };
    countdown();
    this.countdown = setInterval(countdown, 500);
    this.retryTimer = setTimeout(() => this.#connect(), delay);
  }

  #cancelRetry() {
    clearTimeout(this.retryTimer);
    clearInterval(this.countdown);
  }

  #disconnect() {
    this.#cancelRetry();
    const socket = this.socket;
    this.socket = null;
    socket?.close();
    this.attempt = 0;
    this.#state("idle", "Offline");
  }

  #state(state, text) {
    this.els.connection.dataset.state = state;
    this.els.connection.textContent = text;
  }

  #receive(message) {
    // the live marker follows live positions; refined re-emissions belong to history
    if (message.type === "position" && !message.smoothed) this.#position(message);
    else if (message.type === "zone") this.#zoneEvent(message);
  }

  #position(p) {
    let device = this.devices.get(p.device_id);
    if (!device) {
      device = { trail: [], marker: null, row: null };
      this.devices.set(p.device_id, device);
      this.onDevice(p.device_id);
    }
    if (device.last && device.last.floor_id !== p.floor_id) device.trail = [];
    device.last = p;
    device.seenAt = Date.now();
    device.trail.push([p.x, p.y]);
    if (device.trail.length > TRAIL_LENGTH) device.trail.shift();
    this.#draw(p.device_id, device);
    this.#renderRow(p.device_id, device);
    this.#renderCount();
  }

  #draw(id, device) {
    const here = device.last && device.last.floor_id === this.floorId;
    if (!here) {
      device.marker?.remove();
      device.marker = null;
      return;
    }
    device.marker ??= new DeviceMarker(this.plan, "live", id);
    device.marker.update(device.last, device.trail);
    device.marker.setStale(Date.now() - device.seenAt > STALE_AFTER_MS);
  }

  #renderRow(id, device) {
    if (!device.row) {
      const row = document.createElement("li");
      row.dataset.device = id;
      row.innerHTML =
        '<span class="swatch"></span><span class="name"></span>' +
        '<span class="meta"></span><span class="age"></span>';
      row.querySelector(".name").textContent = id;
      row.addEventListener("click", () => {
        const p = device.last;
        if (p.floor_id === this.floorId) this.plan.centreOn(p.x, p.y);
      });
      device.row = row;
      const rows = [...this.els.devices.children];
      const next = rows.find((r) => r.dataset.device > id);
      this.els.devices.insertBefore(row, next ?? null);
    }
    const p = device.last;
    device.row.querySelector(".swatch").replaceChildren(shapeIcon(p.method, deviceColour(id)));
    const elsewhere = p.floor_id === this.floorId ? "" : ` · floor ${p.floor_id ?? "?"}`;
    device.row.querySelector(".meta").textContent =
      `${p.method} · ±${p.accuracy.toFixed(1)} m${elsewhere}`;
    device.row.classList.toggle("elsewhere", p.floor_id !== this.floorId);
    this.#renderAge(device);
  }

  #renderAges() {
    for (const device of this.devices.values()) {
      this.#renderAge(device);
      device.marker?.setStale(Date.now() - device.seenAt > STALE_AFTER_MS);
    }
  }

  #renderAge(device) {
    const age = Date.now() - device.seenAt;
    device.row.querySelector(".age").textContent = formatAge(age);
    device.row.classList.toggle("stale", age > STALE_AFTER_MS);
  }

  #renderCount() {
    this.els.count.textContent = this.devices.size ? String(this.devices.size) : "";
    this.els.noDevices.hidden = this.devices.size > 0;
  }

  #zoneEvent(event) {
    const item = document.createElement("li");
    item.dataset.event = event.event;
    item.innerHTML =
      '<time></time><span class="badge"></span><span class="zone"></span><span class="who"></span>';
    item.querySelector("time").textContent = new Date(event.t).toLocaleTimeString();
    item.querySelector(".badge").textContent = event.event;
    item.querySelector(".zone").textContent = event.zone;
    item.querySelector(".who").textContent = event.device_id;
    this.els.events.prepend(item);
    while (this.els.events.children.length > MAX_EVENTS) this.els.events.lastChild.remove();
    this.els.noEvents.hidden = true;
  }
}

function formatAge(ms) {
  const s = Math.max(0, Math.floor(ms / 1000));
  if (s < 60) return `${s} s ago`;
  if (s < 3600) return `${Math.floor(s / 60)} min ago`;
  return `${Math.floor(s / 3600)} h ago`;
}
