// The dashboard's entry point: sign-in, site and floor selection, tabs, and the wiring
// between the plan and the live, replay, admin, accuracy and survey guidance views.

import { AccuracyOverlay } from "./accuracy.js";
import { AdminView } from "./admin.js";
import { OutputsView } from "./outputs.js";
import { AnalyticsView } from "./analytics.js";
import { Api, ApiError, forgetKey, storedKey, storeKey } from "./api.js";
import { METHOD_SHAPES, shapeIcon } from "./devices.js";
import { GuidanceOverlay } from "./guidance.js";
import { LiveView } from "./live.js";
import { PlanView } from "./plan.js";
import { ReplayView } from "./replay.js";
import { WallIndex } from "./walls.js";

const $ = (id) => document.getElementById(id);

class Dashboard {
  constructor(api, role) {
    this.api = api;
    this.role = role;
    this.siteId = null;
    this.floorId = null;
    this.selection = 0;
    this.plan = new PlanView($("plan"));
    this.live = new LiveView(
      api,
      this.plan,
      {
        connection: $("connection"),
        devices: $("devices"),
        noDevices: $("no-devices"),
        count: $("device-count"),
        events: $("zone-events"),
        noEvents: $("no-events"),
      },
      { onDevice: (id) => this.#knownDevice(id) },
    );
    this.replay = new ReplayView(api, this.plan, {
      form: $("replay-form"),
      device: $("replay-device"),
      from: $("replay-from"),
      to: $("replay-to"),
      status: $("replay-status"),
      play: $("replay-play"),
      speed: $("replay-speed"),
      slider: $("replay-slider"),
      time: $("replay-time"),
      where: $("replay-where"),
    });
    // the accuracy and survey guidance overlays share the plan's heatmap layer: one at a time
    this.accuracy = new AccuracyOverlay(
      api,
      this.plan,
      {
        toggle: $("accuracy-toggle"),
        options: $("accuracy-options"),
        tech: $("accuracy-tech"),
        z: $("accuracy-z"),
        cell: $("accuracy-cell"),
        status: $("accuracy-status"),
        scale: $("accuracy-scale"),
        legend: $("accuracy-ramp"),
        scaleTop: $("accuracy-top"),
      },
      { onShow: () => this.guidance.turnOff() },
    );
    this.guidance = new GuidanceOverlay(
      api,
      this.plan,
      {
        toggle: $("guidance-toggle"),
        status: $("guidance-status"),
        scale: $("guidance-scale"),
        legend: $("guidance-ramp"),
        scaleTop: $("guidance-top"),
      },
      { onShow: () => this.accuracy.turnOff() },
    );
    this.analytics = new AnalyticsView(api, this.plan, {
      form: $("analytics-form"),
      from: $("analytics-from"),
      to: $("analytics-to"),
      cell: $("analytics-cell"),
      zone: $("analytics-zone"),
      bucket: $("analytics-bucket"),
      status: $("analytics-status"),
      chart: $("analytics-chart"),
    });
    this.admin = new AdminView(
      api,
      this.plan,
      {
        siteForm: $("site-form"),
        siteId: $("new-site-id"),
        siteName: $("new-site-name"),
        siteResult: $("site-result"),
        uploadForm: $("upload-form"),
        floorId: $("upload-floor-id"),
        file: $("upload-file"),
        uploadResult: $("upload-result"),
        banner: $("preview-banner"),
        back: $("preview-back"),
      },
      {
        currentSite: () => this.siteId,
        siteCreated: (id) => this.#shown(this.loadSites(id)),
        floorStored: (id) => this.#shown(this.selectSite(this.siteId, id)),
      },
    );
    this.outputs = new OutputsView(
      api,
      { list: $("outputs"), status: $("outputs-status"), refresh: $("outputs-refresh") },
      () => this.siteId,
    );
    $("site").addEventListener("change", (e) => this.#shown(this.selectSite(e.target.value)));
    $("floor").addEventListener("change", (e) => this.#shown(this.selectFloor(e.target.value)));
    $("zoom-in").addEventListener("click", () => this.plan.zoomAt(1.5));
    $("zoom-out").addEventListener("click", () => this.plan.zoomAt(1 / 1.5));
    $("zoom-fit").addEventListener("click", () => this.plan.fit());
    $("sign-out").addEventListener("click", () => {
      forgetKey();
      location.replace(location.pathname);
    });
    for (const tab of document.querySelectorAll("[role=tab]")) {
      tab.addEventListener("click", () => this.showTab(tab.dataset.panel));
    }
    $("role").textContent = role === "admin" ? "admin" : "viewer";
    $("tab-admin").hidden = role !== "admin";
    buildLegend($("legend-methods"));
  }

  showTab(name) {
    if (name !== "admin") this.admin.closePreview();
    for (const tab of document.querySelectorAll("[role=tab]")) {
      const selected = tab.dataset.panel === name;
      tab.setAttribute("aria-selected", String(selected));
      $(`panel-${tab.dataset.panel}`).hidden = !selected;
    }
    this.live.setVisible(name !== "replay");
    this.replay.setVisible(name === "replay");
    if (name === "replay") this.replay.defaultRange();
    this.analytics.setVisible(name === "analytics");
    this.outputs.setVisible(name === "admin");
    if (name === "analytics") this.analytics.defaultRange();
  }

  /** List the sites and select `preferred` (else the one in the URL, else the first). */
  async loadSites(preferred) {
    const sites = await this.api.sites();
    const select = $("site");
    select.replaceChildren(
      ...sites.map((s) => new Option(s.name === s.id ? s.id : `${s.name} (${s.id})`, s.id)),
    );
    const wanted = preferred ?? urlState().get("site");
    const site = sites.find((s) => s.id === wanted) ?? sites[0];
    await this.selectSite(site?.id ?? null);
  }

  /** Select a site, list its floors and select `preferred` (else the URL's, else the first). */
  async selectSite(siteId, preferred) {
    const selection = ++this.selection;
    this.siteId = siteId;
    $("site").value = siteId ?? "";
    this.live.setSite(siteId);
    this.replay.setSite(siteId);
    this.outputs.siteChanged();
    const floors = siteId ? await this.api.floors(siteId) : [];
    if (selection !== this.selection) return;
    $("floor").replaceChildren(
      ...floors.map((f) => new Option(`${f.name ?? f.floor_id} · level ${f.level}`, f.floor_id)),
    );
    $("floor").disabled = !floors.length;
    const wanted = preferred ?? urlState().get("floor");
    const floor = floors.find((f) => f.floor_id === wanted) ?? floors[0];
    if (!floor) {
      this.#empty(
        siteId
          ? `Site “${siteId}” has no floor map yet.${this.#adminHint("upload one")}`
          : `No sites yet.${this.#adminHint("create one")}`,
      );
    }
    await this.selectFloor(floor?.floor_id ?? null);
  }

  async selectFloor(floorId) {
    const selection = ++this.selection;
    this.admin.closePreview();
    this.floorId = floorId;
    $("floor").value = floorId ?? "";
    $("upload-floor-id").value = floorId ?? "";
    setUrlState({ site: this.siteId, floor: floorId });
    const svg = $("plan");
    if (floorId) {
      const doc = await this.api.floor(this.siteId, floorId);
      if (selection !== this.selection) return;
      const { bounds } = this.plan.drawMap("map", doc);
      this.analytics.setFloor(this.siteId, floorId, doc);
      this.plan.walls = new WallIndex(doc);
      this.plan.setBounds(bounds);
      svg.dataset.floor = floorId;
      $("plan-empty").hidden = true;
    } else {
      this.plan.clear("map");
      this.plan.walls = null;
      delete svg.dataset.floor;
    }
    this.live.setFloor(floorId);
    this.replay.setFloor(floorId);
    this.accuracy.setFloor(this.siteId, floorId);
    this.guidance.setFloor(this.siteId, floorId);
  }

  /** Show on the plan why a selection could not be loaded. */
  async #shown(loading) {
    try {
      await loading;
    } catch (error) {
      this.#empty(`Could not load it: ${error.message}`);
    }
  }

  #empty(text) {
    $("plan-empty").textContent = text;
    $("plan-empty").hidden = false;
  }

  #adminHint(action) {
    return this.role === "admin" ? ` Use the Admin tab to ${action}.` : "";
  }

  #knownDevice(id) {
    $("known-devices").append(new Option(id));
    if (!$("replay-device").value) $("replay-device").value = id;
  }
}

/** List the marker shape of each method (each device has its own colour). */
function buildLegend(list) {
  for (const method of Object.keys(METHOD_SHAPES)) {
    const item = document.createElement("li");
    item.append(shapeIcon(method, "#475569"), method);
    list.append(item);
  }
}

function urlState() {
  return new URLSearchParams(location.hash.slice(1));
}

function setUrlState(values) {
  const state = new URLSearchParams();
  for (const [name, value] of Object.entries(values)) if (value) state.set(name, value);
  history.replaceState(null, "", `#${state}`);
}

async function open(key) {
  const api = new Api(key);
  await api.sites();
  const role = await api.role();
  storeKey(key);
  $("signin").hidden = true;
  $("app").hidden = false;
  const dashboard = new Dashboard(api, role);
  await dashboard.loadSites();
}

function signInError(error) {
  if (error instanceof ApiError && error.status === 401) return "Unknown key.";
  if (error instanceof ApiError && error.status === 403) {
    return "Device keys cannot open the dashboard: use a viewer or admin key.";
  }
  return `Could not sign in: ${error.message}`;
}

function showSignIn(message = "") {
  $("app").hidden = true;
  $("signin").hidden = false;
  $("signin-error").textContent = message;
  $("key").focus();
}

$("signin-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  $("signin-error").textContent = "";
  try {
    await open($("key").value.trim());
  } catch (error) {
    showSignIn(signInError(error));
  }
});

const saved = storedKey();
if (saved) {
  open(saved).catch((error) => {
    forgetKey();
    showSignIn(signInError(error));
  });
} else {
  showSignIn();
}
