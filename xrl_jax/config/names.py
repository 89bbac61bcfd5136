"""The names every part of xrl-jax shares: the scenarios, agents and presets, the choices of the
string settings, the log-σ bounds of the Gaussian policies (docs/algorithms.md §2.1, §2.3), and which
agent settings are traced, sweepable or host-only."""

ALGOS = ("sac", "dsac", "xsac", "xdsac")
ENVS = ("country_road", "tracking", "intersection")
PRESETS = ("paper", "quick", "smoke")
CONTINUOUS_ALGOS = ("sac", "xsac")
DISCRETE_ALGOS = ("dsac", "xdsac")
MIXTURE_ALGOS = ("xsac", "xdsac")
# The on-policy family (xrl_jax.ppo): PPO and its mixture policy XPPO, each with continuous (squashed
# Gaussian) and discrete (categorical) actions. Each has an off-policy twin with its actor and policy.
ON_POLICY_ALGOS = ("ppo", "dppo", "xppo", "xdppo")
ACTOR_TWIN = {"ppo": "sac", "dppo": "dsac", "xppo": "xsac", "xdppo": "xdsac"}
TRAINED_ALGOS = (*ALGOS, *ON_POLICY_ALGOS)  # what run.py trains; ALGOS are the paper's (its campaign)
# Each explainable agent against the agent it extends (the report's P(X > baseline)).
BASELINES = {"xsac": "sac", "xdsac": "dsac", "xppo": "ppo", "xdppo": "dppo"}
FEATURE_EXTRACTORS = ("deepset", "flat_pe")  # names of xrl_jax.networks.make_extractor
CRITIC_LOSSES = ("huber", "l2")
TRUNCATION_MODES = ("drop", "bootstrap", "terminal")
MIXTURE_LOG_STD_MIN = -5.0  # lower log σ clip of the mixture policies (§2.3: σ ≥ e^-5 keeps densities sane)
SAC_LOG_STD_MIN = -20.0  # lower log σ clip of the baseline SAC actor (§2.1)
LOG_STD_MAX = 2.0  # upper log σ clip of every Gaussian policy (§2.1, §2.3)
MAX_VEHICLES = 8  # vehicle slots of the intersection env (envs.intersection.MAX_AGENTS; a test checks)

# Fields that become traced leaves of the agent state (``AgentState.hparams``; can differ per vmapped
# seed / sweep member). init_alpha only sets the initial ``AgentState.log_alpha``, itself a traced leaf.
TRACED_FIELDS = ("actor_lr", "critic_lr", "alpha_lr", "gamma", "tau", "kappa", "target_entropy")
# What ``--sweep`` may vary within one compiled program: the traced fields and the initial α.
SWEEPABLE_FIELDS = (*TRACED_FIELDS, "init_alpha")
# The on-policy family's traced fields (xrl_jax.ppo.PPOHyperParams), all of them sweepable.
ON_POLICY_TRACED_FIELDS = ("actor_lr", "critic_lr", "gamma", "gae_lambda", "clip_eps", "ent_coef", "kappa")
# Settings that only the host loop reads: they change neither the compiled code nor the results.
HOST_ONLY_FIELDS = ("max_group_size", "memory_budget_gb", "checkpoint_minutes", "num_devices")
