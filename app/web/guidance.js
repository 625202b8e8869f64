// Survey guidance overlay: the positioning error to expect in each cell of the floor, from
// the latest radio-map build's held-out survey scans (docs/api.md, "Survey guidance"),
// drawn under the plan so an admin sees where to survey next.

import { ApiError } from "./api.js";
import { hasShape, showGrid } from "./grid.js";
import { ERROR_ALPHA, ERROR_RAMP, NO_VALUE, rampColour, rampGradient } from "./ramp.js";

export class GuidanceOverlay {
  constructor(api, plan, els, { onShow } = {}) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.onShow = onShow ?? (() => {});
    this.siteId = null;
    this.floorId = null;
    this.request = 0;
    this.drawn = false;
    els.toggle.addEventListener("change", () => {
      if (els.toggle.checked) this.onShow();
      this.refresh();
    });
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
    this.drawn = false;
    this.els.scale.hidden = true;
    this.#status("", "off");
  }

  async refresh() {
    const request = ++this.request;
    // the layer is shared: clear it when ours is on it or is about to be, not otherwise
    if (this.drawn || this.els.toggle.checked) this.plan.clear("heatmap");
    this.drawn = false;
    this.els.scale.hidden = true;
    if (!this.els.toggle.checked || !this.floorId) {
      this.#status("", "off");
      return;
    }
    this.#status("Loading…", "loading");
    try {
      const grid = await this.api.surveyGuidance(this.siteId, this.floorId);
      if (request === this.request) this.#render(grid);
    } catch (error) {
      if (request !== this.request) return;
      if (error instanceof ApiError && error.status === 404) {
        this.#status(`No survey guidance: ${error.message}`, "unavailable");
      } else {
        this.#status(`Survey guidance failed: ${error.message}`, "error");
      }
    }
  }

  #render(grid) {
    const [ny, nx] = checkedShape(grid);
    // the scale runs to twice the build's "needs more survey" threshold: the threshold is
    // the ramp's middle (yellow), the same top as the server's PNG
    const top = 2 * grid.params.high_error_m;
    const { node, coloured } = showGrid(this.plan, "heatmap", grid, ny, nx, (r, c) => {
      // outside the walkable area the cell stays transparent
      if (!grid.walkable[r][c]) return null;
      const e = grid.expected_error_m[r][c];
      return e === null ? NO_VALUE : [...rampColour(ERROR_RAMP, e / top), ERROR_ALPHA];
    });
    node.dataset.shape = `${ny}x${nx}`;
    node.dataset.cells = String(coloured);
    node.dataset.overlay = "guidance";
    this.drawn = true;
    const s = grid.summary;
    const mean = s.mean_expected_error_m;
    this.#status(
      `Build of ${new Date(grid.built_at).toLocaleString()}: expected error ` +
        `${mean === null ? "–" : `${mean.toFixed(1)} m`} on average where surveyed; ` +
        `${percent(s.unsurveyed_share)} of the walkable area unsurveyed, ` +
        `${percent(s.high_error_share)} above ${grid.params.high_error_m} m`,
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

/** Return [ny, nx] when the answer's grids have that shape; throw otherwise. */
function checkedShape(grid) {
  const [ny, nx] = grid?.shape ?? [];
  const rowsOk = (rows) => hasShape(rows, ny, nx);
  if (
    !(ny > 0 && nx > 0 && grid.cell > 0 && grid.params?.high_error_m > 0) ||
    !rowsOk(grid.walkable) ||
    !rowsOk(grid.expected_error_m)
  ) {
    throw new Error("the answer does not match the contract (shape, cell, grids)");
  }
  return [ny, nx];
}

function percent(share) {
  return share === null ? "–" : `${Math.round(100 * share)}%`;
}
