"""Output writers: animated glTF binary (``glb``) and plain arrays (``npz``)."""
from inference.export.glb import write_glb
from inference.export.npz import read_npz, write_npz
from inference.export.tracks import BodyTrack, GarmentTrack

__all__ = ["BodyTrack", "GarmentTrack", "read_npz", "write_glb", "write_npz"]
