"""napari-dslrxr: digital radiography from a DSLR photographing an X-ray scintillator."""

__version__ = "0.1.0"
