"""The rules of W's perturbed episode kinds (`training.baseline`'s module docstring), one set of numbers
for both backends: the host's `_noisy_prior_episode` / `_random_episode` and their on-device twins in
`training.baseline_device`."""

KINDS = ("prior", "prior", "prior-noisy", "prior-noisy", "random")  # episode i is of kind KINDS[i % 5]

NOISE_SPEED = (0.01, 0.04)  # m/s: range of the per-episode std of the belt-speed setpoints' noise
NOISE_POSITION = (0.001, 0.004)  # m: range of the per-episode std of the carriage steps' noise
P_RANDOM_NOISY = 0.1  # probability of a uniformly random action per step (prior-noisy)
MODES = ("turn", "translate", "stop", "any")
MODE_P = (0.45, 0.2, 0.1, 0.25)  # probabilities of the random drive's modes
HOLD = (10, 31)  # steps a random drive's target is held: [10, 31)
TURN_SPREAD = 0.01  # m/s: std of the noise on a turning target's two speeds
SPEED_MIN = 0.03  # m/s: the slowest target speed
TRANSLATE_CAP = 0.12  # m/s: the fastest translation
RANDOM_SPEED = 0.12  # m/s: the range of a uniformly random action's belt speeds (random drive)
X_TURN_BACK = 0.12  # m: past this |x| a target moving further out is replaced
X_CENTRE = 0.05  # m: past this |x| a translation heads back to the centre
BALANCE_CORRECT = 0.015  # m: a carriage step corrects a balance error past this
STEP_MIN = 0.002  # m: the smallest correcting carriage step
P_RANDOM_DRIVE = 0.25  # probability of a uniformly random action per step (random drive)
