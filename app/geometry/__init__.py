"""Floor maps: validation, the walkable area, rasters for the engine, importers."""
