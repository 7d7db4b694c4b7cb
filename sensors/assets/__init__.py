"""Procedural world assets: vehicles, people (and the closed primitives they are made of).

See docs/assets.md for the catalogue, the sources of the dimensions and the licences.
"""
