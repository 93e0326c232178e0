"""napari widgets: one module per stage, thin clients of the headless core."""
