"""The one vocabulary of TensorDict keys, written once and used everywhere.

A 3D-LAST batch (``TensorDict`` with batch size ``[B]``, time second)::

    states [B, T, 9]   measurements [B, T, 3] (NaN = missed detection)   mode [B, T] int64
    turn_rate [B, T] (rad/s)   r [B]   dt [B]   and optionally t [B, T] (s)

``dt`` is a track's nominal interval; ``t``, where present, the time of each scan (any spacing,
strictly increasing along T). Without ``t`` scan ``k`` is at ``k dt``. What every tracker reads is
``immnet.data.times.scan_intervals(batch)``: the interval before each scan ``[B, T]``.

A method's output (``TensorDict [B]``): ``state [B, T, 9]`` and, where it has them, ``mode_probs
[B, T, 4]`` over the data modes (0 CV, 1 CA, 2 CT+, 3 CT-) and ``state_cov [B, T, 9, 9]``, the covariance the
filter holds for its state (asked for with ``return_cov``).

One tracker step (``immnet.stages``) reads and writes nested keys that say where a value came from.
"""

# --- data -----------------------------------------------------------------------------------
STATES = "states"
MEASUREMENTS = "measurements"
MODE = "mode"
TURN_RATE = "turn_rate"
R = "r"
DT = "dt"
TIME = "t"
MEAS_COV = "meas_cov"  # each detection's measurement covariance R [B, T, 3, 3] (m^2; NaN where missed), in the radar's ENU frame

# --- a method's output ------------------------------------------------------------------------
STATE = "state"
MODE_PROBS = "mode_probs"
STATE_COV = "state_cov"  # the fused state's covariance P_{t|t} [B, T, 9, 9], from the methods that keep one (return_cov)
LOGLIK = "loglik"  # each scan's measurement log-likelihood under the tracker's prediction [B, T] (IMMNet.predictive_loglik)
MEMBER_PROBS = "member_probs"  # a bank's probability of each member network per scan [B, T, K] (immnet.tracking.bank)

# --- an IMMNet rollout's outputs over time (TensorDict [B, T]), besides ``state`` ------------------
ROLLOUT_EXPERT_PROBS = "expert_probs"  # mu_t over the experts [B, T, M]
ROLLOUT_MODE_LOGITS = "mode_logits"  # the classifier's logits [B, T, M]
ROLLOUT_EXPERT_POST = "expert_post"  # each expert's posterior x_{t|t}^(i) [B, T, M, 9]

# --- IMMNet as a policy of a TorchRL environment (immnet.data.env.LASTEnv) -------------------------
ACTION = "action"  # the policy's action: its state estimate x_{t|t} [B, 9]
IS_INIT = "is_init"  # [B, 1] bool, True where a track (re)starts (TorchRL's InitTracker)

# --- one tracker step (immnet.stages) ---------------------------------------------------------
MEASUREMENT = "measurement"  # z_t [B, 3]
INTERVAL = "interval"  # the time since the previous scan [B] (s); absent: the network's nominal dt
TRUE_MODE = ("truth", "mode")  # an oracle's input: the truth's data mode at this scan [B] int64 (the clairvoyant filters)
TRUE_TURN_RATE = ("truth", "turn_rate")  # an oracle's input: the truth's turn rate at this scan [B] (rad/s)
TRUE_RESTART = ("truth", "restart")  # an oracle's input: the truth draws its mode's parameter anew at this scan [B] bool
PREV_MEASUREMENT = ("memory", "measurement")  # z_{t-1} [B, 3]
FUSED = ("fused", "state")  # x_{t|t} [B, 9]; read as x_{t-1|t-1} at the start of a step
FUSED_COV = ("fused", "cov")  # P_{t|t} [B, 9, 9], where the experts carry a covariance (filter experts, the analytic gain)
OUTPUT = ("output", "state")  # the estimate a step reports where a learned output correction follows the fusion [B, 9]
OUTPUT_HIDDEN = ("memory", "output_hidden")  # the output correction's recurrent state [B, L, H] (immnet.stages.correct)
OUTPUT_SEEN = ("memory", "output_seen")  # 1 once the output correction has seen a track's first detection [B]
COV_SCALE = ("memory", "cov_scale")  # covariance consistency: the reported covariance's scale per track [B] (docs/immnet.md)
PREV_FUSED = ("memory", "fused")  # x_{t-2|t-2} [B, 9]
EXPERT_PRIOR = ("expert", "prior")  # x_{t|t-1}^(i) [B, M, 9]
PREV_EXPERT_PRIOR = ("memory", "prior")  # x_{t-1|t-2}^(i) [B, M, 9]
EXPERT_GAIN = ("expert", "gain")  # K^(i) [B, M, 9, 3]
EXPERT_POST = ("expert", "post")  # x_{t|t}^(i) [B, M, 9]
EXPERT_CORRECTION = ("expert", "correction")  # a learned additive correction of x_{t|t}^(i) [B, M, 9] (state_correction)
EXPERT_HIDDEN = ("expert", "hidden")  # recurrent states of the gain networks
EXPERT_COV = ("expert", "cov")  # P^(i) for the analytic gain [B, M, 9, 9]
EXPERT_RATE = ("expert", "rate")  # a filter expert's own turn rate w^(i) [B, M] (rad/s)
EXPERT_LOGLIK = ("expert", "loglik")  # a filter expert's log N(nu; 0, S) [B, M] (modes per group: [B, G, M])
EXPERT_NIS = ("expert", "nis")  # and its normalized innovation squared nu^T S^-1 nu [B, M] (0 where no detection)
EXPERT_ROBUST_WEIGHT = ("expert", "robust_weight")  # Huber's weight [B, M] (1: plain); [B, M, 3] with modes per group
EXPERT_RATE_GAIN = ("expert", "rate_gain")  # its gain row for w [B, M, 3]
EXPERT_MIXED = ("expert", "mixed")  # a filter expert's input point [x~, w~] from the interaction [B, M, 10]
EXPERT_MIXED_COV = ("expert", "mixed_cov")  # and its covariance [B, M, 10, 10]
EXPERT_AUG_PRIOR_COV = ("expert", "aug_prior_cov")  # a filter expert's prior covariance of [x, w] [B, M, 10, 10]
EXPERT_AUG_COV = ("expert", "aug_cov")  # and its posterior covariance [B, M, 10, 10]
NOISE_VAR = ("memory", "r2")  # running estimate of the measurement variance r^2 [B]
NOISE_SUM = ("memory", "r2_sum")  # its sum of (d^3 z)^2 / 20 [B]
NOISE_COUNT = ("memory", "r2_count")  # and the number of terms [B]
Q_SCALE = ("memory", "q_log_scale")  # adaptive process noise: log lambda per track [B] (immnet.imm.adaptive)
Z_HISTORY = ("memory", "z_history")  # z_{t-1}, z_{t-2}, z_{t-3} [B, 3, 3] (NaN = none)
INTERVAL_HISTORY = ("memory", "interval_history")  # the intervals z_{t-2} -> z_{t-1}, z_{t-3} -> z_{t-2} [B, 2] (s)
MODE_LOGITS = ("mode", "logits")  # [B, M] (modes per group: [B, G, M])
MODE_TRANSITION = ("mode", "transition")  # a guarded interaction's transition matrix Pi[b, from, to] [B, M, M]
GUARD_FRESH = ("expert", "speed_fresh")  # a guarded interaction: prior share of each expert entered at a speed bound [B, M]
EXPERT_PROBS = ("mode", "probs")  # mu_t [B, M] (modes per group: [B, G, M], IMMNet(modes=...))
HISTORY = ("memory", "history")  # classifier window [B, W, 12]: z_tau and x_{tau-1|tau-1}
HISTORY_LEN = ("memory", "history_len")  # valid entries of the window [B]
HISTORY_INTERVAL = ("memory", "history_interval")  # the interval before each entry's scan [B, W] (s)
PREV_INTERVAL = ("memory", "interval")  # the previous scan's interval [B] (s)
AGE = ("memory", "age")  # scans since the track started, capped at 2 [B]
START_SCANS = ("memory", "start_scans")  # scans since a starting track's first detection [B]
START_TIME = ("memory", "start_time")  # the time since a starting track's first detection [B] (s)
STARTING = ("start", "tracks")  # the tracks that start at this scan (age below the start's detections) [B] bool (immnet.stages.start)
REACQUIRE_COUNT = ("memory", "reacquire_count")  # re-acquisition: the track's run of far detections [B] (immnet.imm.reacquire)
REACQUIRE_PLOT = ("memory", "reacquire_plot")  # the run's last detection [B, 3]
REACQUIRE_COV = ("memory", "reacquire_cov")  # its covariance [B, 3, 3]
REACQUIRE_ELAPSED = ("memory", "reacquire_elapsed")  # the time since it [B] (s)
ROBUST_SPARE = ("memory", "robust_spare")  # 1 where the track's last plot lay beyond Huber's k of every filter [B] (per group [B, G]; immnet.imm.kalman)
REACQUIRE = ("expert", "reacquire")  # the tracks whose run of far detections restarts them at this scan [B] bool
START_CARRY = ("start", "carry")  # what each starting track carries after this scan, a TensorDict [B] like the carry
