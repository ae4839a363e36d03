"""3D observation: voxel grids, the Bayesian occupancy grid, the hierarchical colour hull, silhouette carving."""

from torchtrack.occupancy.bayes import BayesConfig, BayesianGrid, Occupancy
from torchtrack.occupancy.grid import GridSpec, VoxelLookup, capture_views, grid_from_rig
from torchtrack.occupancy.hull import (HierarchicalHull, HullConfig, SparseVoxels, hierarchical_hull,
                                       hull_from_images)
from torchtrack.occupancy.silhouette import SilhouetteCarving

__all__ = ["BayesConfig", "BayesianGrid", "GridSpec", "capture_views", "HierarchicalHull", "HullConfig", "Occupancy",
           "SilhouetteCarving", "SparseVoxels", "VoxelLookup", "grid_from_rig", "hierarchical_hull", "hull_from_images"]
