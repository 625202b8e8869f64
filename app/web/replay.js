// Replay view: a device's stored positions over a time range, played back on the plan.

import { DeviceMarker, svgElement } from "./plan.js";
import { brokenPath } from "./walls.js";

const TRAIL_LENGTH = 20;
const DEFAULT_RANGE_MS = 15 * 60_000;

export class ReplayView {
  constructor(api, plan, els) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.siteId = null;
    this.floorId = null;
    this.positions = [];
    this.t = null;
    this.playing = false;
    this.marker = null;
    els.form.addEventListener("submit", (event) => {
      event.preventDefault();
      this.load();
    });
    els.play.addEventListener("click", () => (this.playing ? this.pause() : this.play()));
    els.slider.addEventListener("input", () => this.seek(Number(els.slider.value)));
  }

  /** Fill the time range with the last quarter of an hour when it is empty. */
  defaultRange() {
    if (this.els.from.value && this.els.to.value) return;
    const now = Date.now();
    this.els.from.value = toLocalInput(now - DEFAULT_RANGE_MS);
    this.els.to.value = toLocalInput(now);
  }

  /** Devices belong to their site: the history is read from the one shown. */
  setSite(siteId) {
    this.siteId = siteId;
  }

  setFloor(floorId) {
    this.floorId = floorId;
    this.#drawPath();
    this.#drawMarker();
  }

  setVisible(visible) {
    this.plan.setVisible("replay", visible);
    if (!visible) this.pause();
  }

  async load() {
    const device = this.els.device.value.trim();
    const from = new Date(this.els.from.value).getTime();
    const to = new Date(this.els.to.value).getTime();
    if (!this.siteId || !device || !(from < to)) {
      this.#status("Pick a site, a device and a time range that ends after it starts.", "error");
      return;
    }
    this.pause();
    this.#status("Loading…", "loading");
    let answer;
    try {
      answer = await this.api.history(this.siteId, device, from, to);
    } catch (error) {
      this.#status(`Could not load the history: ${error.message}`, "error");
      return;
    }
    this.positions = answer.items;
    this.t = null;
    const { slider, play } = this.els;
    slider.disabled = play.disabled = !this.positions.length;
    if (!this.positions.length) {
      this.#status(`No positions of ${device} in this range.`, "empty");
      this.setFloor(this.floorId);
      this.els.time.textContent = "";
      return;
    }
    const first = this.positions[0].t;
    const last = this.positions.at(-1).t;
    slider.min = first;
    slider.max = last;
    const floors = [...new Set(this.positions.map((p) => p.floor_id ?? "?"))].join(", ");
    this.#status(
      `${this.positions.length} positions of ${device}, ` +
        `${formatTime(first)} – ${formatTime(last)}` +
        ` (floor ${floors})${answer.truncated ? "; only the first ones are shown" : ""}.`,
      "loaded",
    );
    this.#drawPath();
    this.seek(first);
  }

  seek(t) {
    this.t = t;
    this.els.slider.value = t;
    this.els.time.textContent = formatTime(t);
    this.#drawMarker();
  }

  play() {
    if (!this.positions.length) return;
    const last = this.positions.at(-1).t;
    if (this.t >= last) this.seek(this.positions[0].t);
    this.playing = true;
    this.els.play.textContent = "Pause";
    let before = performance.now();
    const step = (now) => {
      if (!this.playing) return;
      // measurement time advances `speed` times as fast as the wall clock
      const t = Math.min(last, this.t + (now - before) * Number(this.els.speed.value));
      before = now;
      this.seek(t);
      if (t >= last) this.pause();
      else requestAnimationFrame(step);
    };
    requestAnimationFrame(step);
  }

  pause() {
    this.playing = false;
    this.els.play.textContent = "Play";
  }

  /** Draw the whole recording's path on the shown floor, one run per stay on it, the pen
   * lifted where a leg would cross a wall. */
  #drawPath() {
    const { world } = this.plan.clear("replay");
    this.marker = null;
    const runs = [];
    let run = null;
    for (const p of this.positions) {
      if (p.floor_id !== this.floorId) {
        run = null;
        continue;
      }
      if (!run) runs.push((run = []));
      run.push([p.x, p.y]);
    }
    const d = runs.map((points) => brokenPath(points, this.plan.walls)).join("");
    if (d) svgElement("path", { class: "replay-path", d }, world);
  }

  #drawMarker() {
    const i = lastAtOrBefore(this.positions, this.t);
    const p = i >= 0 ? this.positions[i] : null;
    const here = p && p.floor_id === this.floorId;
    this.els.where.textContent =
      p && !here ? `At this time the device is on floor ${p.floor_id}.` : "";
    if (!here) {
      this.marker?.remove();
      this.marker = null;
      return;
    }
    const trail = this.positions
      .slice(Math.max(0, i - TRAIL_LENGTH + 1), i + 1)
      .filter((q) => q.floor_id === this.floorId)
      .map((q) => [q.x, q.y]);
    this.marker ??= new DeviceMarker(this.plan, "replay", p.device_id);
    this.marker.update(p, trail);
  }

  #status(text, state) {
    this.els.status.textContent = text;
    this.els.status.dataset.state = state;
  }
}

/** Return the index of the last position with t ≤ `t` (binary search), or −1. */
function lastAtOrBefore(positions, t) {
  let low = 0;
  let high = positions.length;
  while (low < high) {
    const mid = (low + high) >> 1;
    if (positions[mid].t <= t) low = mid + 1;
    else high = mid;
  }
  return low - 1;
}

/** Return a datetime-local input's value (local time, seconds) for epoch milliseconds. */
function toLocalInput(ms) {
  const local = new Date(ms - new Date(ms).getTimezoneOffset() * 60_000);
  return local.toISOString().slice(0, 19);
}

function formatTime(ms) {
  return new Date(ms).toLocaleTimeString();
}
