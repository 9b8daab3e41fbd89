"""AniSDF: fused-granularity neural surfaces with anisotropic spherical Gaussian encoding."""

__version__ = "0.1.0"
