"""CaraPost for Python: facial motion capture from multi-camera marker video to labelled 3D data."""

__version__ = "0.1.0"
