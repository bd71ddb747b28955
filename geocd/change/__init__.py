"""Change products shared by every method: regions (polygons), layers, plots."""
