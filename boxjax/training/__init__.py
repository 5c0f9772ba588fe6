"""Data and training pipelines: `dataset` (H's exploration dataset), `estimator` (train, evaluate and ship
H), `baseline` (W's episodes and training), `pets` (PETS's training), `calibration` (the paper prior's
force map, by simulation). Each is what a `boxjax train-*` / `calibrate` command runs."""
