"""Vision Lab: an interactive 3D computer-vision lab (see ../shared/DESIGN.md)."""

__version__ = "0.1.0"
