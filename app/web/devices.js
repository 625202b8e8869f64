// How a device is drawn: a colour of its own (so three phones are three trails), and a
// marker whose shape says which method placed it.

// Distinct hues that read on the light plan; devices take them in the order they appear.
const PALETTE = [
  "#2563eb",
  "#dc2626",
  "#16a34a",
  "#9333ea",
  "#ea580c",
  "#0891b2",
  "#db2777",
  "#65a30d",
  "#b45309",
  "#4f46e5",
];
const assigned = new Map();

/** Return the device's colour: the next unused one of the palette the first time it is seen. */
export function deviceColour(deviceId) {
  if (!assigned.has(deviceId)) assigned.set(deviceId, PALETTE[assigned.size % PALETTE.length]);
  return assigned.get(deviceId);
}

// Marker outlines (px, centred on the position), one per positioning method.
export const METHOD_SHAPES = {
  pf: "M-6.5,0A6.5,6.5 0 1,0 6.5,0A6.5,6.5 0 1,0 -6.5,0Z",
  hmm: "M0,-8L8,0L0,8L-8,0Z",
  ekf: "M-6,-6H6V6H-6Z",
  lsq: "M0,-7.5L7,5.5H-7Z",
  centroid: "M-3.5,-6.5H3.5L7,0L3.5,6.5H-3.5L-7,0Z",
  trackfit: "M0,-7.5L7.1,-2.3L4.4,6.1H-4.4L-7.1,-2.3Z",
};
const OTHER_SHAPE = "M-5,-5L5,5M5,-5L-5,5";

export function methodShape(method) {
  return METHOD_SHAPES[method] ?? OTHER_SHAPE;
}

/** Return a small inline SVG of a method's marker in `colour`, for lists and the legend. */
export function shapeIcon(method, colour) {
  const ns = "http://www.w3.org/2000/svg";
  const svg = document.createElementNS(ns, "svg");
  svg.setAttribute("viewBox", "-9 -9 18 18");
  svg.setAttribute("class", "shape-icon");
  const path = document.createElementNS(ns, "path");
  path.setAttribute("d", methodShape(method));
  path.setAttribute("fill", colour);
  svg.append(path);
  return svg;
}
