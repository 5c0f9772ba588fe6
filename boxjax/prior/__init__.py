"""The physics prior: the box's planar motion on the belts predicted from its mass distribution
(paper eqs. 4-14, and the slip-friction variant), in jitted jnp.

Modules: `predictor` (PriorParams, PriorModel, `make_prior`, `predict`, `rollout_sequence`), `contact`
(the support polygon, normal loads and the stability margin), `friction` (the friction law), `force_map`
(the paper variant's calibrated forces, fitted by `boxjax.training.calibration`) and `residual` (a
learned correction on the prior's rollouts). This face re-exports the predictor's public API:
`from boxjax import prior; model = prior.make_prior(masses)`.
"""

from boxjax.prior.contact import (
    Contacts,
    contact_fractions,
    normal_loads,
    polygon_contacts,
    stability_margin,
    voxel_contacts,
)
from boxjax.prior.force_map import ForceMap, default_force_map
from boxjax.prior.friction import dissipation, friction_force
from boxjax.prior.predictor import (
    CONES,
    CONTACTS,
    MARGINS,
    NORMALS,
    VARIANTS,
    PriorModel,
    PriorParams,
    explain,
    make_prior,
    predict,
    rollout,
    rollout_sequence,
)

__all__ = [
    "CONES",
    "MARGINS",
    "CONTACTS",
    "NORMALS",
    "VARIANTS",
    "Contacts",
    "ForceMap",
    "PriorModel",
    "PriorParams",
    "contact_fractions",
    "default_force_map",
    "dissipation",
    "explain",
    "friction_force",
    "make_prior",
    "normal_loads",
    "polygon_contacts",
    "predict",
    "rollout",
    "rollout_sequence",
    "stability_margin",
    "voxel_contacts",
]
