// Accuracy planning overlay: the standard deviation a least-squares fix would have at
// each cell of the floor (docs/api.md, "Planning"), drawn as a heatmap under the plan.

import { ApiError } from "./api.js";
import { hasShape, showGrid } from "./grid.js";
import { ERROR_ALPHA, ERROR_RAMP, NO_VALUE, rampColour, rampGradient } from "./ramp.js";

export class AccuracyOverlay {
  constructor(api, plan, els, { onShow } = {}) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.siteId = null;
    this.floorId = null;
    this.request = 0;
    // before the refresh below: whatever else shared the layer is turned off first
    els.toggle.addEventListener("change", () => {
      if (els.toggle.checked) onShow?.();
    });
    for (const input of [els.toggle, els.tech, els.z, els.cell]) {
      input.addEventListener("change", () => this.refresh());
    }
    els.legend.style.background = rampGradient(ERROR_RAMP);
  }

  setFloor(siteId, floorId) {
    this.siteId = siteId;
    this.floorId = floorId;
    this.refresh();
  }

  /** Untick and forget the overlay without touching the layer another overlay now draws. */
  turnOff() {
    this.request++;
    this.els.toggle.checked = false;
    this.els.options.hidden = true;
    this.els.scale.hidden = true;
    this.#status("", "off");
  }

  async refresh() {
    const request = ++this.request;
    this.plan.clear("heatmap");
    this.els.scale.hidden = true;
    this.els.options.hidden = !this.els.toggle.checked;
    if (!this.els.toggle.checked || !this.floorId) {
      this.#status("", "off");
      return;
    }
    const params = {
      tech: this.els.tech.value,
      z: Number(this.els.z.value),
      cell: Number(this.els.cell.value),
    };
    this.#status("Loading…", "loading");
    try {
      const grid = await this.api.accuracy(this.siteId, this.floorId, params);
      if (request === this.request) this.#render(grid, params);
    } catch (error) {
      if (request !== this.request) return;
      if (error instanceof ApiError && error.status === 404) {
        this.#status(
          `Accuracy map not available on this server (404: ${error.message}).`,
          "unavailable",
        );
      } else {
        this.#status(`Accuracy map failed: ${error.message}`, "error");
      }
    }
  }

  #render(grid, params) {
    const field = horizontalSigma(grid);
    const finite = field.values.filter(Number.isFinite).sort((a, b) => a - b);
    // top of the scale: the 95th percentile rounded up to 0.5 m, so a few edge cells
    // with huge σ do not wash out the rest
    const top = finite.length
      ? Math.max(0.5, Math.ceil(2 * finite[Math.floor(0.95 * (finite.length - 1))]) / 2)
      : 1;
    const { node } = showGrid(this.plan, "heatmap", grid, field.ny, field.nx, (r, c) => {
      const sigma = field.values[r * field.nx + c];
      return Number.isFinite(sigma)
        ? [...rampColour(ERROR_RAMP, sigma / top), ERROR_ALPHA]
        : NO_VALUE;
    });
    node.dataset.shape = `${field.ny}x${field.nx}`;
    const unobservable = field.values.length - finite.length;
    const median = finite.length ? finite[Math.floor(finite.length / 2)] : null;
    this.#status(
      `${params.tech === "uwb" ? "UWB anchors" : "Transmitters"} at z = ${params.z} m: median σ ` +
        `${median === null ? "–" : `${median.toFixed(2)} m`}` +
        (unobservable ? `, ${unobservable} cells unobservable` : ""),
      "shown",
    );
    this.els.scaleTop.textContent = `≥ ${top} m`;
    this.els.scale.hidden = false;
  }

  #status(text, state) {
    this.els.status.textContent = text;
    this.els.status.dataset.state = state;
  }
}

/**
 * Return {ny, nx, values}: the horizontal σ = √(σx² + σy²) (m) of each cell, row by row
 * from y0 up, NaN where the position is unobservable (null in either array).
 */
function horizontalSigma(grid) {
  const [ny, nx] = grid?.shape ?? [];
  const rowsOk = (rows) => hasShape(rows, ny, nx);
  if (!(ny > 0 && nx > 0 && grid.cell > 0 && rowsOk(grid.sigma_x) && rowsOk(grid.sigma_y))) {
    throw new Error("the answer does not match the contract (shape, cell, sigma_x, sigma_y)");
  }
  const values = new Float64Array(ny * nx);
  for (let r = 0; r < ny; r++) {
    for (let c = 0; c < nx; c++) {
      const sx = grid.sigma_x[r][c];
      const sy = grid.sigma_y[r][c];
      // σ = √(σx² + σy²)
      values[r * nx + c] = sx === null || sy === null ? NaN : Math.hypot(sx, sy);
    }
  }
  return { ny, nx, values };
}
