"""NuScenes-GSQA data layer: the on-disk layout, its reader, and the dataset producers."""

from pipelines.data.layout import CAMERAS, TASKS, DataError, DatasetWriter
from pipelines.data.reader import Frame, GSQADataset, Scene

__all__ = ["CAMERAS", "TASKS", "DataError", "DatasetWriter", "Frame", "GSQADataset", "Scene"]
