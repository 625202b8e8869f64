// Where a trail may not be drawn straight: every wall, no-go area's edge and the outline of
// a floor map, indexed on a grid so that testing a trail's leg reads only the walls near it.

const MIN_CELL = 2; // m
const CELLS_ACROSS = 200; // a large floor's grid stays this many cells across
const MAX_CELLS_PER_WALL = 400; // longer walls are tested against every leg instead

export class WallIndex {
  /** Index the uncrossable lines of a floor-map document (GeoJSON in metres). */
  constructor(doc) {
    const segments = [];
    for (const feature of Array.isArray(doc?.features) ? doc.features : []) {
      const kind = feature?.properties?.kind;
      if (kind === "wall" || kind === "barrier" || kind === "outline") {
        for (const line of lines(feature.geometry)) {
          for (let i = 1; i < line.length; i++) segments.push([...line[i - 1], ...line[i]]);
        }
      }
    }
    this.segments = segments;
    const xs = segments.flatMap((s) => [s[0], s[2]]);
    const ys = segments.flatMap((s) => [s[1], s[3]]);
    this.x0 = Math.min(...xs);
    this.y0 = Math.min(...ys);
    const extent = Math.max(Math.max(...xs) - this.x0, Math.max(...ys) - this.y0);
    this.cell = Math.max(MIN_CELL, extent / CELLS_ACROSS);
    this.grid = new Map();
    this.everywhere = [];
    segments.forEach((s, index) => {
      const [i0, j0, i1, j1] = this.#cells(s[0], s[1], s[2], s[3]);
      if ((i1 - i0 + 1) * (j1 - j0 + 1) > MAX_CELLS_PER_WALL) {
        this.everywhere.push(index);
        return;
      }
      for (let i = i0; i <= i1; i++) {
        for (let j = j0; j <= j1; j++) {
          const key = `${i},${j}`;
          if (!this.grid.has(key)) this.grid.set(key, []);
          this.grid.get(key).push(index);
        }
      }
    });
  }

  /** Return whether the straight move from a to b ([x, y]) touches or crosses a wall. */
  crosses(a, b) {
    if (!this.segments.length) return false;
    const [i0, j0, i1, j1] = this.#cells(a[0], a[1], b[0], b[1]);
    const seen = new Set(this.everywhere);
    for (let i = i0; i <= i1; i++) {
      for (let j = j0; j <= j1; j++) {
        for (const index of this.grid.get(`${i},${j}`) ?? []) seen.add(index);
      }
    }
    for (const index of seen) {
      const s = this.segments[index];
      if (segmentsMeet(a, b, [s[0], s[1]], [s[2], s[3]])) return true;
    }
    return false;
  }

  #cells(xa, ya, xb, yb) {
    const i = (x) => Math.floor((x - this.x0) / this.cell);
    const j = (y) => Math.floor((y - this.y0) / this.cell);
    return [i(Math.min(xa, xb)), j(Math.min(ya, yb)), i(Math.max(xa, xb)), j(Math.max(ya, yb))];
  }
}

/**
 * Return an SVG path through `points` ([[x, y], ...]) as the engine gave them, lifting the
 * pen over every leg that would cross a wall of `walls` (a WallIndex, or null for none).
 */
export function brokenPath(points, walls) {
  let d = "";
  points.forEach(([x, y], k) => {
    const lift = k === 0 || (walls && walls.crosses(points[k - 1], points[k]));
    d += `${lift ? "M" : "L"}${x},${y}`;
  });
  return d;
}

function lines(geometry) {
  const c = geometry?.coordinates;
  switch (geometry?.type) {
    case "LineString":
      return [c];
    case "MultiLineString":
    case "Polygon":
      return c;
    case "MultiPolygon":
      return c.flat(1);
    default:
      return [];
  }
}

/** Return the sign of the turn p → q → r: 1 counter-clockwise, −1 clockwise, 0 collinear. */
function turn(p, q, r) {
  // cross product (q − p) × (r − p)
  const cross = (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
  return Math.sign(cross);
}

function within(p, q, r) {
  // r lies in the bounding box of p, q (used when the three are collinear)
  return (
    Math.min(p[0], q[0]) <= r[0] &&
    r[0] <= Math.max(p[0], q[0]) &&
    Math.min(p[1], q[1]) <= r[1] &&
    r[1] <= Math.max(p[1], q[1])
  );
}

/** Return whether segments ab and cd share a point (crossing, touching or overlapping). */
function segmentsMeet(a, b, c, d) {
  const t1 = turn(a, b, c);
  const t2 = turn(a, b, d);
  const t3 = turn(c, d, a);
  const t4 = turn(c, d, b);
  if (t1 !== t2 && t3 !== t4) return true;
  return (
    (t1 === 0 && within(a, b, c)) ||
    (t2 === 0 && within(a, b, d)) ||
    (t3 === 0 && within(c, d, a)) ||
    (t4 === 0 && within(c, d, b))
  );
}
