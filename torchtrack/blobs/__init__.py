"""Blobs: the body appearance model (Gaussian blobs on bones)."""

from torchtrack.blobs.model import BlobModel, BlobSpec, load_blob_specs

__all__ = ["BlobModel", "BlobSpec", "load_blob_specs"]
