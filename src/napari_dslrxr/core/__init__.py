"""Headless core of napari-dslrxr: plain functions and small dataclasses over numpy arrays.

Nothing in this package imports Qt or napari; every stage is usable from scripts and CI.
"""
