"""3D observation: voxel grids, the Bayesian occupancy grid, the hierarchical colour hull, silhouette carving."""

from torchtrack.occupancy.bayes import BayesConfig, BayesianGrid, Occupancy
from torchtrack.occupancy.grid import GridSpec, VoxelLookup, grid_from_rig
from torchtrack.occupancy.silhouette import SilhouetteCarving

__all__ = ["BayesConfig", "BayesianGrid", "GridSpec", "Occupancy", "SilhouetteCarving", "VoxelLookup",
           "grid_from_rig"]
