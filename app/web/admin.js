// Admin view: create a site and upload floor maps. When the server rejects a map, each
// problem is listed with its feature index, kind and reason, and the rejected map is
// drawn with the features it names marked, so the admin sees what to fix and where.

import { ApiError } from "./api.js";

export class AdminView {
  constructor(api, plan, els, { currentSite, siteCreated, floorStored }) {
    this.api = api;
    this.plan = plan;
    this.els = els;
    this.currentSite = currentSite;
    this.siteCreated = siteCreated;
    this.floorStored = floorStored;
    els.siteForm.addEventListener("submit", (event) => {
      event.preventDefault();
      this.createSite();
    });
    els.uploadForm.addEventListener("submit", (event) => {
      event.preventDefault();
      this.upload();
    });
    els.back.addEventListener("click", () => this.closePreview());
  }

  async createSite() {
    const id = this.els.siteId.value.trim();
    const name = this.els.siteName.value.trim() || id;
    let site;
    try {
      site = await this.api.putSite(id, name);
    } catch (error) {
      this.#result(this.els.siteResult, `Could not save the site: ${errorText(error)}`, "error");
      return;
    }
    this.#result(this.els.siteResult, `Site “${site.name}” (${site.id}) saved.`, "ok");
    this.els.siteForm.reset();
    await this.siteCreated(site.id);
  }

  async upload() {
    const site = this.currentSite();
    const floorId = this.els.floorId.value.trim();
    const file = this.els.file.files[0];
    this.closePreview();
    if (!site || !floorId || !file) {
      this.#result(this.els.uploadResult, "Pick a site, a floor id and a GeoJSON file.", "error");
      return;
    }
    const text = await file.text();
    this.#result(this.els.uploadResult, `Uploading ${file.name}…`, "loading");
    let summary;
    try {
      summary = await this.api.putFloor(site, floorId, text);
    } catch (error) {
      if (error instanceof ApiError && error.code === "invalid_floor_map") {
        this.#showProblems(text, error);
      } else {
        this.#result(this.els.uploadResult, `Upload failed: ${errorText(error)}`, "error");
      }
      return;
    }
    this.#result(this.els.uploadResult, describeSummary(summary), "ok");
    await this.floorStored(floorId);
  }

  /** Leave the rejected map's drawing and show the stored floor and live devices again. */
  closePreview() {
    if (this.els.banner.hidden) return;
    this.plan.clear("preview");
    this.plan.setVisible("map", true);
    this.plan.setVisible("live", true);
    this.els.banner.hidden = true;
  }

  #showProblems(text, error) {
    const problems = error.details;
    let drawn = new Map();
    const doc = parseJson(text);
    if (doc) {
      // the rejected map alone: its features, not the stored ones or devices moving over them
      this.plan.setVisible("map", false);
      this.plan.setVisible("live", false);
      const result = this.plan.drawMap("preview", doc);
      drawn = result.drawn;
      this.plan.markProblems("preview", problems);
      if (result.bounds) this.plan.fit(result.bounds);
      this.els.banner.hidden = false;
    }
    const box = this.els.uploadResult;
    box.replaceChildren();
    box.dataset.state = "rejected";
    const title = document.createElement("p");
    title.className = "error";
    title.textContent = `Not stored (${error.status}): ${error.message}.`;
    const list = document.createElement("ul");
    list.className = "problems";
    for (const problem of problems) {
      const item = document.createElement("li");
      item.className = "problem";
      const where = document.createElement("strong");
      const reason = document.createElement("span");
      reason.className = "reason";
      reason.textContent = problem.reason;
      if (problem.index === null || problem.index === undefined) {
        where.textContent = "Map";
      } else {
        item.dataset.index = problem.index;
        where.textContent = `Feature #${problem.index} · ${problem.kind ?? "no kind"}`;
        if (drawn.has(problem.index)) {
          item.classList.add("drawn");
          item.title = "Show it on the plan";
          item.addEventListener("click", () => this.plan.focusFeature("preview", problem.index));
        } else {
          reason.textContent += " (cannot be drawn)";
        }
      }
      item.append(where, reason);
      list.append(item);
    }
    box.append(title, list);
  }

  #result(box, text, state) {
    box.replaceChildren();
    box.textContent = text;
    box.dataset.state = state;
  }
}

function describeSummary(s) {
  const [x0, y0, x1, y1] = s.bounds;
  const counts = Object.entries(s.counts)
    .filter(([, n]) => n > 0)
    .map(([kind, n]) => `${n} ${kind}${n === 1 ? "" : "s"}`)
    .join(", ");
  return (
    `Stored floor ${s.floor_id}${s.name ? ` (${s.name})` : ""}, level ${s.level}: ` +
    `${(x1 - x0).toFixed(1)} × ${(y1 - y0).toFixed(1)} m, walkable ` +
    `${s.walkable_area.toFixed(0)} m²; ${counts}.`
  );
}

function errorText(error) {
  if (!(error instanceof ApiError)) return error.message;
  const details = error.details
    .map((d) => (d.loc ? `${d.loc.join(".")}: ${d.msg}` : JSON.stringify(d)))
    .join("; ");
  return `${error.status} ${error.message}${details ? ` (${details})` : ""}`;
}

function parseJson(text) {
  try {
    return JSON.parse(text);
  } catch {
    return null;
  }
}
