// Analytics tab: the floor's heatmap of device-seconds over the plan for a chosen time
// range, and a zone's occupancy over time as a chart (docs/api.md, "Analytics").
// uPlot (app/web/vendor) is a classic script loaded before this module: the global uPlot.

import { ApiError } from "./api.js";
import { showGrid } from "./grid.js";
import { rampColour } from "./ramp.js";

// Few device-seconds pale yellow, many dark red (RGB stops, evenly spaced up to the top).
const RAMP = [
  [255, 255, 178],
  [254, 204, 92],
  [253, 141, 60],
  [240, 59, 32],
  [189, 0, 38],
];
const ALPHA = 190;

export class AnalyticsView {
  constructor(api, plan, els) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.siteId = null;
    this.floorId = null;
    this.zones = [];
    this.chart = null;
    this.drawn = false;
    this.request = 0;
    els.form.addEventListener("submit", (event) => {
      event.preventDefault();
      this.refresh();
    });
  }

  setFloor(siteId, floorId, doc) {
    this.siteId = siteId;
    this.floorId = floorId;
    const zones = (doc?.features ?? [])
      .filter((f) => f.properties?.kind === "zone" && f.properties?.name)
      .map((f) => f.properties.name);
    this.els.zone.replaceChildren(...zones.map((z) => new Option(z, z)));
  }

  /** Put the last day in the range inputs when they are empty. */
  defaultRange() {
    if (this.els.from.value && this.els.to.value) return;
    const to = Date.now();
    this.els.to.value = localInput(to);
    this.els.from.value = localInput(to - 86_400_000);
  }

  async refresh() {
    const request = ++this.request;
    const from = new Date(this.els.from.value).getTime();
    const to = new Date(this.els.to.value).getTime();
    if (!this.floorId || !(to > from)) {
      this.#status("Choose a floor and a range whose end is after its start.", "error");
      return;
    }
    this.#status("Loading…", "loading");
    try {
      const cell = Number(this.els.cell.value);
      const bucket = Number(this.els.bucket.value);
      const zone = this.els.zone.value;
      const [grid, occupancy] = await Promise.all([
        this.api.heatmap(this.siteId, this.floorId, { from, to, cell }),
        zone ? this.api.occupancy(this.siteId, zone, { from, to, bucket }) : null,
      ]);
      if (request !== this.request) return;
      const total = this.#drawHeatmap(grid);
      if (occupancy) this.#drawChart(occupancy);
      this.#status(`${Math.round(total)} device-seconds on this floor`, "shown");
    } catch (error) {
      if (request !== this.request) return;
      const why = error instanceof ApiError ? `${error.status}: ${error.message}` : error.message;
      this.#status(`Analytics failed (${why})`, "error");
    }
  }

  /** Take the heatmap away when the tab is left (the accuracy overlay shares its layer). */
  setVisible(visible) {
    if (visible || !this.drawn) return;
    this.plan.clear("heatmap");
    this.drawn = false;
  }

  #drawHeatmap(grid) {
    const [ny, nx] = grid.shape;
    let top = 0;
    let total = 0;
    for (const row of grid.seconds) {
      for (const v of row) {
        if (v !== null) {
          top = Math.max(top, v);
          total += v;
        }
      }
    }
    const { node } = showGrid(this.plan, "heatmap", grid, ny, nx, (r, c) => {
      const v = grid.seconds[r][c];
      // cells outside the outline, or never visited, stay transparent
      return v === null || v <= 0 ? null : [...rampColour(RAMP, v / (top || 1)), ALPHA];
    });
    node.dataset.total = String(total);
    this.drawn = true;
    return total;
  }

  #drawChart(occupancy) {
    const t = occupancy.buckets.map((b) => b.t / 1000);
    const devices = occupancy.buckets.map((b) => b.devices);
    const entries = occupancy.buckets.map((b) => b.entries);
    this.chart?.destroy();
    this.els.chart.replaceChildren();
    this.els.chart.dataset.points = String(t.length);
    this.els.chart.dataset.devices = String(devices.reduce((a, b) => a + b, 0));
    const width = Math.max(240, this.els.chart.clientWidth || 280);
    // eslint-disable-next-line no-undef
    this.chart = new uPlot(
      {
        width,
        height: 180,
        series: [
          {},
          { label: "devices", stroke: "#2563eb", width: 2 },
          { label: "entries", stroke: "#dc2626", width: 1 },
        ],
        axes: [{}, { label: occupancy.zone }],
      },
      [t, devices, entries],
      this.els.chart,
    );
  }

  #status(text, state) {
    this.els.status.textContent = text;
    this.els.status.dataset.state = state;
  }
}

/** Return the value of a datetime-local input for `ms` in the browser's time zone. */
function localInput(ms) {
  const d = new Date(ms - new Date(ms).getTimezoneOffset() * 60_000);
  return d.toISOString().slice(0, 19);
}
