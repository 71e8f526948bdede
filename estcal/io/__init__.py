"""Files users write: datasets (CSV) and robot files (YAML / URDF)."""
from .dataset import Dataset, DatasetError, dataset_from_arrays, load_dataset, write_dataset

__all__ = ["Dataset", "DatasetError", "load_dataset", "write_dataset", "dataset_from_arrays"]
