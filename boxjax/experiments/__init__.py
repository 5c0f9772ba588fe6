"""The experiments: `evaluation` (random safe and hazardous boxes, paper §4.3: `evaluate`), `comparison`
(the prior against W and PETS, paper Tables 1-2: `compare`), `data_efficiency` (success against training
data), `reproduce` (all of the paper in one run) and `report` (its markdown)."""

from boxjax.experiments.comparison import compare
from boxjax.experiments.evaluation import Evaluation, evaluate, make_boxes, wilson_interval

__all__ = ["Evaluation", "compare", "evaluate", "make_boxes", "wilson_interval"]
