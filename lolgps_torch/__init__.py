"""lolgps_torch: Linear Online Guided Policy Search for URDF robot arms."""

__version__ = "0.1.0"
