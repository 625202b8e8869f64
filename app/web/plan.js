// The floor plan: an SVG drawing of a floor map (GeoJSON in the local frame: metres,
// x east, y north) with pan (drag) and zoom (wheel).
//
// Each layer has two groups. Its world group shares one transform (metres to pixels,
// y flipped so north is up) and holds areas, lines, trails and accuracy circles. Its
// screen group holds symbols and labels that keep their size in pixels: each is
// pinned to a world point (data-x, data-y) and moved whenever the view changes.

import { deviceColour, methodShape } from "./devices.js";
import { brokenPath } from "./walls.js";

const NS = "http://www.w3.org/2000/svg";
// The heatmap lies over the map's floor and under its walls' ink (multiplied, see CSS).
const LAYERS = ["map", "heatmap", "preview", "replay", "live"];
// Areas first, walls on top; unknown kinds (only in rejected maps) above areas.
const WORLD_ORDER = ["outline", "room", "zone", "barrier", "other", "wall"];
const SYMBOLS = {
  transmitter: "M0,-5L5,0L0,5L-5,0Z",
  anchor: "M-4,-4H4V4H-4Z",
  locator: "M-4.5,0A4.5,4.5 0 1,0 4.5,0A4.5,4.5 0 1,0 -4.5,0Z",
  other: "M-4,-4L4,4M4,-4L-4,4",
};
// Room around the floor when fitted (px): the cards floating over the plan stay off it.
const PAD = { top: 68, right: 28, bottom: 76, left: 28 };
const MIN_SCALE = 0.05; // px per metre
const MAX_SCALE = 2000;

/** Create an SVG element with attributes, appended to `parent` when given. */
export function svgElement(tag, attrs = {}, parent = null) {
  const node = document.createElementNS(NS, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  if (parent) parent.appendChild(node);
  return node;
}

export class PlanView {
  constructor(svg) {
    this.svg = svg;
    this.k = 1;
    this.tx = 0;
    this.ty = 0;
    this.bounds = null;
    this.userMoved = false;
    this.pending = false;
    this.features = {};
    this.walls = null; // the shown floor's WallIndex: trails are not drawn through walls
    this.#defs();
    this.world = svgElement("g", { class: "world" }, svg);
    this.screen = svgElement("g", { class: "screen" }, svg);
    this.layers = {};
    for (const name of LAYERS) {
      this.layers[name] = {
        world: svgElement("g", { "data-layer": name }, this.world),
        screen: svgElement("g", { "data-layer": name }, this.screen),
      };
    }
    this.#panAndZoom();
    new ResizeObserver(() => (this.userMoved ? this.applyView() : this.fit())).observe(svg);
  }

  #defs() {
    const defs = svgElement("defs", {}, this.svg);
    const hatch = svgElement(
      "pattern",
      {
        id: "hatch",
        width: 8,
        height: 8,
        patternUnits: "userSpaceOnUse",
        patternTransform: "rotate(45)",
      },
      defs,
    );
    svgElement("rect", { width: 8, height: 8, class: "hatch-bg" }, hatch);
    svgElement("line", { x1: 0, y1: 0, x2: 0, y2: 8, class: "hatch-line" }, hatch);
  }

  #panAndZoom() {
    let drag = null;
    this.svg.addEventListener("pointerdown", (event) => {
      if (event.button !== 0) return;
      drag = { x: event.clientX, y: event.clientY, tx: this.tx, ty: this.ty };
      this.svg.setPointerCapture(event.pointerId);
      this.svg.classList.add("dragging");
    });
    this.svg.addEventListener("pointermove", (event) => {
      if (!drag) return;
      this.tx = drag.tx + event.clientX - drag.x;
      this.ty = drag.ty + event.clientY - drag.y;
      this.userMoved = true;
      this.requestView();
    });
    const release = () => {
      drag = null;
      this.svg.classList.remove("dragging");
    };
    this.svg.addEventListener("pointerup", release);
    this.svg.addEventListener("pointercancel", release);
    this.svg.addEventListener(
      "wheel",
      (event) => {
        event.preventDefault();
        const box = this.svg.getBoundingClientRect();
        const factor = Math.exp(-event.deltaY * 0.0015);
        this.zoomAt(factor, event.clientX - box.left, event.clientY - box.top);
      },
      { passive: false },
    );
    this.svg.addEventListener("dblclick", () => this.fit());
  }

  /** Return the layer's {world, screen} groups. */
  layer(name) {
    return this.layers[name];
  }

  /** Empty a layer and forget its features. */
  clear(name) {
    const layer = this.layers[name];
    layer.world.replaceChildren();
    layer.screen.replaceChildren();
    delete this.features[name];
    return layer;
  }

  setVisible(name, visible) {
    const layer = this.layers[name];
    layer.world.style.display = visible ? "" : "none";
    layer.screen.style.display = visible ? "" : "none";
  }

  /**
   * Draw a floor map's features into a layer and return the indices drawn.
   *
   * Anything that is not valid GeoJSON geometry with finite coordinates is
   * skipped, so a rejected upload can be drawn as far as it can be.
   */
  drawMap(name, doc) {
    const { world, screen } = this.clear(name);
    const groups = {};
    for (const kind of WORLD_ORDER) {
      groups[kind] = svgElement("g", { class: `kind-${kind}` }, world);
    }
    const labels = svgElement("g", { class: "labels" }, screen);
    const points = svgElement("g", { class: "points" }, screen);
    const drawn = new Map();
    let outline = null;
    const features = Array.isArray(doc?.features) ? doc.features : [];
    features.forEach((feature, index) => {
      const props = feature?.properties ?? {};
      const kind = typeof props.kind === "string" ? props.kind : "other";
      const shape = geometryShape(feature?.geometry);
      if (!shape) return;
      const attrs = { "data-index": index, "data-kind": kind, class: `feature kind-${kind}` };
      let node;
      if (shape.point) {
        node = svgElement("g", attrs, points);
        const symbol = SYMBOLS[kind] ?? SYMBOLS.other;
        svgElement("path", { d: symbol, class: `symbol tech-${props.tech ?? "none"}` }, node);
        this.pin(node, shape.point[0], shape.point[1]);
      } else {
        const group = groups[kind] ?? groups.other;
        node = svgElement("path", { ...attrs, d: shape.d, "fill-rule": "evenodd" }, group);
        if (shape.closed && (kind === "room" || kind === "zone") && props.name) {
          const [x, y] = shape.anchor;
          // a zone often repeats a room's name and shape: put its label under the room's
          const dy = kind === "zone" ? 15 : 0;
          const label = svgElement("text", { class: `label label-${kind}`, y: dy }, labels);
          label.textContent = String(props.name);
          this.pin(label, x, y);
        }
      }
      svgElement("title", {}, node).textContent = describe(kind, props, index);
      drawn.set(index, { bounds: shape.bounds, anchor: shape.anchor });
      if (kind === "outline" && !outline) outline = shape.bounds;
    });
    this.features[name] = drawn;
    return { drawn, bounds: outline ?? unionBounds([...drawn.values()].map((f) => f.bounds)) };
  }

  /** Mark the features that problems name and put a badge with the index next to each. */
  markProblems(name, problems) {
    const drawn = this.features[name] ?? new Map();
    const badges = svgElement("g", { class: "badges" }, this.layers[name].screen);
    for (const index of new Set(problems.map((p) => p.index))) {
      if (index === null || !drawn.has(index)) continue;
      for (const node of this.#featureNodes(name, index)) node.classList.add("problem");
      const [x, y] = drawn.get(index).anchor;
      const badge = svgElement("g", { class: "badge", "data-problem": index }, badges);
      const text = svgElement("text", { x: 8, y: -8 }, badge);
      text.textContent = `#${index}`;
      this.pin(badge, x, y);
    }
  }

  /** Zoom to a drawn feature and make it blink briefly. */
  focusFeature(name, index) {
    const feature = this.features[name]?.get(index);
    if (!feature) return;
    const [x0, y0, x1, y1] = feature.bounds;
    const margin = Math.max(2, 0.3 * Math.max(x1 - x0, y1 - y0));
    this.fit([x0 - margin, y0 - margin, x1 + margin, y1 + margin]);
    this.userMoved = true;
    for (const node of this.#featureNodes(name, index)) {
      node.classList.remove("flash");
      void node.getBoundingClientRect();
      node.classList.add("flash");
    }
  }

  #featureNodes(name, index) {
    const { world, screen } = this.layers[name];
    const selector = `[data-index="${index}"]`;
    return [...world.querySelectorAll(selector), ...screen.querySelectorAll(selector)];
  }

  /** Fit the bounds [x0, y0, x1, y1] (m) into the view; the last bounds when none given. */
  fit(bounds = this.bounds) {
    if (!bounds) return;
    if (bounds === this.bounds) this.userMoved = false;
    const width = this.svg.clientWidth;
    const height = this.svg.clientHeight;
    if (!width || !height) return;
    const [x0, y0, x1, y1] = bounds;
    const innerWidth = Math.max(width - PAD.left - PAD.right, 1);
    const innerHeight = Math.max(height - PAD.top - PAD.bottom, 1);
    // k = the largest scale at which the bounds fit inside the padded view
    this.k = clamp(
      Math.min(innerWidth / Math.max(x1 - x0, 1e-3), innerHeight / Math.max(y1 - y0, 1e-3)),
      MIN_SCALE,
      MAX_SCALE,
    );
    // centre of the bounds → centre of the padded view (screen y = ty − k·y)
    this.tx = PAD.left + innerWidth / 2 - (this.k * (x0 + x1)) / 2;
    this.ty = PAD.top + innerHeight / 2 + (this.k * (y0 + y1)) / 2;
    this.applyView();
  }

  /** Set the floor's bounds and show all of it. */
  setBounds(bounds) {
    this.bounds = bounds;
    this.fit(bounds);
  }

  /** Zoom by `factor` keeping the world point under the screen point (sx, sy) still. */
  zoomAt(factor, sx = this.svg.clientWidth / 2, sy = this.svg.clientHeight / 2) {
    const k = clamp(this.k * factor, MIN_SCALE, MAX_SCALE);
    const f = k / this.k;
    this.tx = sx - f * (sx - this.tx);
    this.ty = sy - f * (sy - this.ty);
    this.k = k;
    this.userMoved = true;
    this.requestView();
  }

  /** Move the view so that world point (x, y) is at the centre. */
  centreOn(x, y) {
    this.tx = this.svg.clientWidth / 2 - this.k * x;
    this.ty = this.svg.clientHeight / 2 + this.k * y;
    this.userMoved = true;
    this.applyView();
  }

  /** Return the screen point (px) of the world point (x, y) (m). */
  project(x, y) {
    return [this.k * x + this.tx, this.ty - this.k * y];
  }

  /** Place a screen-group element at the world point (x, y) and keep it there. */
  pin(node, x, y) {
    node.dataset.x = x;
    node.dataset.y = y;
    const [sx, sy] = this.project(x, y);
    node.setAttribute("transform", `translate(${sx.toFixed(1)},${sy.toFixed(1)})`);
  }

  requestView() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.applyView();
    });
  }

  applyView() {
    this.world.setAttribute("transform", `matrix(${this.k},0,0,${-this.k},${this.tx},${this.ty})`);
    for (const node of this.screen.querySelectorAll("[data-x]")) {
      this.pin(node, Number(node.dataset.x), Number(node.dataset.y));
    }
  }

  /** Show an image covering [x, x + width] × [y, y + height] (m), its first row at y. */
  showImage(name, { href, x, y, width, height }) {
    const { world } = this.clear(name);
    return svgElement(
      "image",
      { href, x, y, width, height, preserveAspectRatio: "none", class: "raster" },
      world,
    );
  }
}

/**
 * A device on the plan: trail and accuracy circle in metres, marker and heading in pixels.
 * Its colour is the device's own; the marker's shape says which method placed it.
 */
export class DeviceMarker {
  constructor(plan, layerName, deviceId) {
    const { world, screen } = plan.layer(layerName);
    this.plan = plan;
    this.trail = svgElement("path", { class: "trail", "data-device": deviceId }, world);
    this.circle = svgElement("circle", { class: "accuracy" }, world);
    this.node = svgElement("g", { class: "device", "data-device": deviceId }, screen);
    const arrow = "M0,-20L5.5,-10.5L-5.5,-10.5Z";
    this.arrow = svgElement("path", { class: "heading", d: arrow }, this.node);
    this.dot = svgElement("path", { class: "dot" }, this.node);
    const label = svgElement("text", { class: "device-label", x: 10, y: 4 }, this.node);
    label.textContent = deviceId;
    const colour = deviceColour(deviceId);
    for (const node of [this.node, this.trail, this.circle]) {
      node.style.setProperty("--colour", colour);
    }
  }

  /** Draw the position message `p` with the recent positions `trail` ([[x, y], ...]). */
  update(p, trail) {
    this.node.dataset.method = p.method;
    this.node.dataset.t = p.t;
    this.dot.setAttribute("d", methodShape(p.method));
    // the engine's path as it came, the pen lifted where a leg would cross a wall
    this.trail.setAttribute("d", brokenPath(trail, this.plan.walls));
    this.circle.setAttribute("cx", p.x);
    this.circle.setAttribute("cy", p.y);
    this.circle.setAttribute("r", Math.max(p.accuracy, 0));
    if (p.heading === null || p.heading === undefined) {
      this.arrow.style.display = "none";
    } else {
      this.arrow.style.display = "";
      // heading is clockwise from +y, which is screen up: an SVG rotation turns the same way
      this.arrow.setAttribute("transform", `rotate(${p.heading})`);
    }
    this.plan.pin(this.node, p.x, p.y);
  }

  setStale(stale) {
    this.node.classList.toggle("stale", stale);
    this.trail.classList.toggle("stale", stale);
    this.circle.classList.toggle("stale", stale);
  }

  remove() {
    this.trail.remove();
    this.circle.remove();
    this.node.remove();
  }
}

function describe(kind, props, index) {
  const name = props.name ?? props.id;
  const extra = props.tech ? ` (${props.tech})` : "";
  return `${kind}${name !== undefined ? `: ${name}` : ""}${extra} · feature #${index}`;
}

function isPosition(p) {
  return Array.isArray(p) && p.length >= 2 && Number.isFinite(p[0]) && Number.isFinite(p[1]);
}

function isLine(line, min) {
  return Array.isArray(line) && line.length >= min && line.every(isPosition);
}

/**
 * Return {d, closed, bounds, anchor} of a line or area geometry, or {point, bounds, anchor}
 * of a Point; null when it cannot be drawn.
 */
function geometryShape(geometry) {
  const c = geometry?.coordinates;
  let lines;
  let closed = false;
  switch (geometry?.type) {
    case "Point":
      if (!isPosition(c)) return null;
      return { point: c, bounds: [c[0], c[1], c[0], c[1]], anchor: [c[0], c[1]] };
    case "LineString":
      lines = [c];
      break;
    case "MultiLineString":
      lines = c;
      break;
    case "Polygon":
      lines = c;
      closed = true;
      break;
    case "MultiPolygon":
      lines = Array.isArray(c) ? c.flat(1) : null;
      closed = true;
      break;
    default:
      return null;
  }
  if (!Array.isArray(lines) || !lines.length || !lines.every((l) => isLine(l, 2))) return null;
  const d = lines
    .map((l) => `M${l.map(([x, y]) => `${x},${y}`).join("L")}${closed ? "Z" : ""}`)
    .join("");
  const bounds = unionBounds(lines.map(lineBounds));
  const anchor = closed ? ringCentroid(lines[0]) ?? centre(bounds) : centre(bounds);
  return { d, closed, bounds, anchor };
}

function lineBounds(line) {
  const xs = line.map((p) => p[0]);
  const ys = line.map((p) => p[1]);
  return [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
}

function unionBounds(list) {
  if (!list.length) return null;
  return [
    Math.min(...list.map((b) => b[0])),
    Math.min(...list.map((b) => b[1])),
    Math.max(...list.map((b) => b[2])),
    Math.max(...list.map((b) => b[3])),
  ];
}

function centre([x0, y0, x1, y1]) {
  return [(x0 + x1) / 2, (y0 + y1) / 2];
}

/** Return the area centroid of a ring, or null when its area is zero. */
function ringCentroid(ring) {
  let area = 0;
  let cx = 0;
  let cy = 0;
  for (let i = 0; i < ring.length; i++) {
    const [x0, y0] = ring[i];
    const [x1, y1] = ring[(i + 1) % ring.length];
    // shoelace: a = x0·y1 − x1·y0; C = Σ (p0 + p1)·a / (3 Σ a)
    const a = x0 * y1 - x1 * y0;
    area += a;
    cx += (x0 + x1) * a;
    cy += (y0 + y1) * a;
  }
  if (Math.abs(area) < 1e-12) return null;
  return [cx / (3 * area), cy / (3 * area)];
}

function clamp(value, low, high) {
  return Math.min(high, Math.max(low, value));
}
