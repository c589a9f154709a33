"""Datasets: config, plan + manifest, resumable parallel builder, verifier, batch loader.

    config = load_dataset_config("experiments/configs/dataset-tiny.toml")
    manifest = build_dataset(config, "data/tiny")          # resumable; executor='ray' on a cluster
    report = verify_dataset("data/tiny")                   # report.ok, report.problems
    for batch in DatasetLoader("data/tiny", "train", batch_size=4, crop_size=16, seed=0):
        batch.input.color, batch.reference.color            # (B, h, w, 3) float32
"""

from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig, ProceduralConfig, SplitConfig, load_dataset_config
from jaxden.data.layout import Crop, Item, Manifest, load_manifest, plan_dataset
from jaxden.data.loader import Batch, DatasetLoader, dihedral, dihedral_frame, dihedral_motion
from jaxden.data.verify import Problem, VerifyReport, verify_dataset

__all__ = [
    "Batch",
    "Crop",
    "DatasetConfig",
    "DatasetLoader",
    "Item",
    "Manifest",
    "Problem",
    "ProceduralConfig",
    "SplitConfig",
    "VerifyReport",
    "build_dataset",
    "dihedral",
    "dihedral_frame",
    "dihedral_motion",
    "load_dataset_config",
    "load_manifest",
    "plan_dataset",
    "verify_dataset",
]
