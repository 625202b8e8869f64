// Grids of cells over a floor plan: the accuracy map, the survey guidance and the
// analytics heatmap all arrive as (ny, nx) arrays with row 0 at the grid's y0.

/** Whether `rows` is `ny` arrays of `nx` values each. */
export function hasShape(rows, ny, nx) {
  return (
    Array.isArray(rows) &&
    rows.length === ny &&
    rows.every((r) => Array.isArray(r) && r.length === nx)
  );
}

/**
 * Draw a grid on the plan's `layer`: `colourOf(r, c)` gives a cell's [r, g, b, a], or null
 * to leave it transparent. Returns the image node and how many cells were coloured.
 */
export function showGrid(plan, layer, grid, ny, nx, colourOf) {
  const canvas = document.createElement("canvas");
  canvas.width = nx;
  canvas.height = ny;
  const context = canvas.getContext("2d");
  const image = context.createImageData(nx, ny);
  let coloured = 0;
  for (let r = 0; r < ny; r++) {
    for (let c = 0; c < nx; c++) {
      const rgba = colourOf(r, c);
      if (rgba === null) continue;
      image.data.set(rgba, 4 * (r * nx + c));
      coloured++;
    }
  }
  context.putImageData(image, 0, 0);
  // canvas row 0 is grid row 0 (at y0); the plan's flipped y puts it at the bottom
  const node = plan.showImage(layer, {
    href: canvas.toDataURL(),
    x: grid.origin[0],
    y: grid.origin[1],
    width: nx * grid.cell,
    height: ny * grid.cell,
  });
  return { node, coloured };
}
