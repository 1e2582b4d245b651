"""Principal-axis management (paper "Principal Axis Management"): creation by mean shift, soft
association by EM, update/merge/delete after BA. Pure numpy; directions are sign-invariant lines."""

from papl_mapper.axes.association import associate, mean_angles_deg, pack_observations
from papl_mapper.axes.config import AxesConfig
from papl_mapper.axes.creation import Candidate, CreationResult, create_axes, mean_shift_modes
from papl_mapper.axes.update import AxisState, UpdateResult, remap_weights, update_axes

__all__ = [
    "AxesConfig",
    "AxisState",
    "Candidate",
    "CreationResult",
    "UpdateResult",
    "associate",
    "create_axes",
    "mean_angles_deg",
    "mean_shift_modes",
    "pack_observations",
    "remap_weights",
    "update_axes",
]
