"""Scenes: wisp geometry and sources (generated, strands HDF5, USD), head motion, rank-local rest state."""
