"""Data layer: dataset parsers, the normalised :class:`Scene`, cameras and ray batches."""

from anisdf.data.cameras import Cameras
from anisdf.data.dataparsers import detect_format, load_scene, parse_dataset
from anisdf.data.inspect import inspect_dataset
from anisdf.data.rays import RayBatch, RayDataset
from anisdf.data.scene import FORMATS, Scene

__all__ = [
    "FORMATS",
    "Cameras",
    "RayBatch",
    "RayDataset",
    "Scene",
    "detect_format",
    "inspect_dataset",
    "load_scene",
    "parse_dataset",
]
