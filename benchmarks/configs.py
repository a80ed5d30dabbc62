"""
What the benchmark runs: the environments (threshold, step budget, evaluation period) and the algorithm configs.

Adding an NFQ config is one entry in :data:`NFQ_CONFIGS`: a name mapped to ``{env id or "*": NFQ kwargs}``.
Kwargs are passed to ``NFQ("MlpPolicy", env, seed=seed, **kwargs)``, written as in the RL Zoo's YAML files:
``policy_kwargs`` may be a string such as ``"dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)"``
(evaluated with ``th``, ``nn`` and ``dict`` in scope), ``learning_rate`` may be ``"lin_1e-3"`` (linear schedule),
and three extra keys are understood: ``n_envs`` (training envs, default 1), ``policy`` (default ``"MlpPolicy"``)
and ``n_timesteps`` (this config's step budget on that env, instead of :data:`ENVS`' budget).
Keep the values plain data (numbers, strings, lists, dicts): they are hashed into the job key and stored in
the results file.
"""

import importlib.metadata
import importlib.util
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml

from sb3_nfq.configs import read_entry

AlgoKind = Literal["nfq", "reference", "dqn"]

#: Every env of the given config (an entry for a specific env id takes precedence).
ALL_ENVS = "*"


@dataclass(frozen=True)
class EnvSpec:
    """
    :param threshold: "solved" when the mean return of ``N_EVAL_EPISODES`` greedy episodes reaches this
    :param budget: default env-step budget of the NFQ configs and the reference (DQN uses the Zoo's ``n_timesteps``)
    :param eval_every: evaluate at the first round end (NFQ, reference) or rollout start (DQN) at or after each
        multiple of this many env steps
    """

    threshold: float
    budget: int
    eval_every: int = 1024


#: The four benchmark envs. Thresholds: gymnasium's ``reward_threshold`` of each env (CartPole's 475 is also the
#: book's criterion).
#: Budgets are for NFQ and the reference: the book's NFQ needs ~230k-280k steps on CartPole, so 300k
#: (examples/solve_cartpole.py's default); the others get the same order of magnitude (2.5x to 5x the Zoo's DQN
#: budget on each env), LunarLander the most because its episodes are up to 1000 steps long.
#: Evaluation periods: every 1024 steps (the textbook's round) where an evaluation is cheap. Acrobot's and
#: LunarLander's unsolved episodes run 500 and 1000 steps, so one evaluation plays up to 50k and 100k env steps there
#: (measured ~1.9 s and ~4.5 s on one core, vs ~0.5 s for a textbook NFQ round): every 2048 and 5120 steps.
ENVS: dict[str, EnvSpec] = {
    "CartPole-v1": EnvSpec(threshold=475.0, budget=300_000),
    "Acrobot-v1": EnvSpec(threshold=-100.0, budget=300_000, eval_every=2048),
    "MountainCar-v0": EnvSpec(threshold=-110.0, budget=300_000),
    "LunarLander-v3": EnvSpec(threshold=200.0, budget=500_000, eval_every=5120),
}

#: Greedy episodes per evaluation (learning curve, solve criterion and final score).
N_EVAL_EPISODES = 100

#: The RL Zoo's DQN budget (``n_timesteps`` in rl_zoo3's hyperparams/dqn.yml) on each env: the budget of the
#: growing-memory configs, so that they get the same number of env steps as ``dqn-zoo``.
ZOO_DQN_BUDGETS: dict[str, int] = {
    "CartPole-v1": 50_000,
    "Acrobot-v1": 100_000,
    "MountainCar-v0": 120_000,
    "LunarLander-v3": 100_000,
}

#: nfq-shared's settings (sb3_nfq/hyperparams/nfq-shared.yml, where they are described), without the budget: the
#: base the tuned configs and tuning candidates start from.
GROWING_MEMORY_CONFIG: dict[str, Any] = {
    key: value for key, value in read_entry("nfq-shared", "CartPole-v1").items() if key != "n_timesteps"
}

#: NFQ configs: name -> {env id or ALL_ENVS: kwargs for NFQ}.
NFQ_CONFIGS: dict[str, dict[str, dict[str, Any]]] = {
    # The textbook settings, i.e. NFQ's defaults, on every env.
    "nfq-book": {ALL_ENVS: {}},
    # One tuned config per env: the winner of benchmarks/tune_nfq.py's sweep on that env (tuning seeds 100-102 on
    # CartPole, 100-101 elsewhere; results in benchmarks/results/tuning_per_env.jsonl).
    "nfq-tuned": {
        # "shared-256x256-lr-2.3e-3-rounds-128": GROWING_MEMORY_CONFIG with the Zoo DQN's network and learning rate
        # (256-256, 2.3e-3), refitted every 128 steps instead of 256.
        "CartPole-v1": {
            **GROWING_MEMORY_CONFIG,
            "learning_rate": 2.3e-3,
            "policy_kwargs": "dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)",
            "train_freq": 128,
            "n_timesteps": ZOO_DQN_BUDGETS["CartPole-v1"],
        },
        # "book-eps-1-to-0.05": the textbook NFQ, with epsilon decaying 1 -> 0.05 over the first 30k steps.
        "Acrobot-v1": {"exploration_initial_eps": 1.0, "exploration_final_eps": 0.05, "exploration_fraction": 0.1},
        # "shared-memory-10k-gamma-0.98": GROWING_MEMORY_CONFIG with the Zoo DQN's MountainCar memory and discount.
        "MountainCar-v0": {
            **GROWING_MEMORY_CONFIG,
            "buffer_size": 10_000,
            "gamma": 0.98,
            "n_timesteps": ZOO_DQN_BUDGETS["MountainCar-v0"],
        },
        # "low-replay-256x256-huber-lr-5e-4-memory-50k-zoo-eps": 4 refits of a 50k memory every 1024 steps (16x
        # fewer than GROWING_MEMORY_CONFIG), the Zoo DQN's 256-256 network and exploration, Huber loss, Adam 5e-4.
        "LunarLander-v3": {
            **GROWING_MEMORY_CONFIG,
            "exploration_final_eps": 0.1,
            "exploration_fraction": 0.12,
            "train_freq": 1024,
            "gradient_steps": 4,
            "buffer_size": 50_000,
            "loss": "huber",
            "learning_rate": 5e-4,
            "policy_kwargs": "dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)",
            "n_timesteps": ZOO_DQN_BUDGETS["LunarLander-v3"],
        },
    },
    # ONE config for all four envs (sb3_nfq/hyperparams/nfq-shared.yml).
    "nfq-shared": {env_id: read_entry("nfq-shared", env_id) for env_id in ZOO_DQN_BUDGETS},
}

#: The plain-PyTorch reference (benchmarks/reference_nfq.py): kwargs for ``ReferenceNFQ``.
REFERENCE_CONFIGS: dict[str, dict[str, dict[str, Any]]] = {"reference-nfq": {ALL_ENVS: {}}}

#: SB3's DQN with the RL Zoo's tuned hyperparameters (rl_zoo3's hyperparams/dqn.yml), n_timesteps as the budget.
DQN_ZOO = "dqn-zoo"

#: Keys of the Zoo's YAML that change the env or the training loop. None is set for the four envs here
#: (checked when read); rather than half-support them, a config that sets one is refused.
ZOO_UNSUPPORTED_KEYS = (
    "normalize",
    "env_wrapper",
    "vec_env_wrapper",
    "frame_stack",
    "callback",
    "env_kwargs",
    "monitor_kwargs",
)


@dataclass(frozen=True)
class ResolvedConfig:
    """
    One algorithm's settings on one env.

    :param algo: config name (``nfq-book``, ``dqn-zoo``, ...)
    :param kind: which trainer runs it: ``nfq`` (sb3_nfq.NFQ), ``reference`` (ReferenceNFQ) or ``dqn`` (SB3 DQN)
    :param env_id: gymnasium env id
    :param kwargs: constructor kwargs as plain data (``n_timesteps`` removed; ``n_envs``/``policy`` kept)
    :param budget: env-step budget
    :param threshold: solve threshold
    :param eval_every: evaluation period in env steps
    :param source: where the values come from (for the record)
    """

    algo: str
    kind: AlgoKind
    env_id: str
    kwargs: dict[str, Any]
    budget: int
    threshold: float
    eval_every: int
    source: str = ""


def algorithm_names() -> list[str]:
    """:return: every algorithm config the runner knows, in report order"""
    return [*NFQ_CONFIGS, *REFERENCE_CONFIGS, DQN_ZOO]


def zoo_hyperparams_path() -> Path:
    """:return: the installed rl_zoo3 package's ``hyperparams/dqn.yml`` (found without importing rl_zoo3)"""
    spec = importlib.util.find_spec("rl_zoo3")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            "dqn-zoo needs the rl_zoo3 package: the zoo extra, pip install '.[zoo]' in a checkout"
        )
    return Path(next(iter(spec.submodule_search_locations))) / "hyperparams" / "dqn.yml"


def zoo_dqn_hyperparams(env_id: str) -> dict[str, Any]:
    """
    :param env_id: gymnasium env id
    :return: the Zoo's DQN entry for this env, as written in the YAML (strings kept as strings)
    """
    path = zoo_hyperparams_path()
    with path.open() as file:
        table = yaml.safe_load(file)
    if env_id not in table:
        raise KeyError(f"{path} has no DQN hyperparameters for {env_id}")
    entry = dict(table[env_id])
    present = [key for key in ZOO_UNSUPPORTED_KEYS if key in entry]
    if present:
        raise NotImplementedError(
            f"The Zoo's DQN entry for {env_id} sets {present}, which this runner does not apply "
            "(none of the four benchmark envs uses them)."
        )
    return entry


def _per_env(table: dict[str, dict[str, Any]], name: str, env_id: str) -> dict[str, Any]:
    if env_id in table:
        return dict(table[env_id])
    if ALL_ENVS in table:
        return dict(table[ALL_ENVS])
    raise KeyError(f"config {name!r} has no entry for {env_id} (and no {ALL_ENVS!r} entry)")


def resolve(algo: str, env_id: str) -> ResolvedConfig:
    """
    :param algo: an algorithm config name (see :func:`algorithm_names`)
    :param env_id: one of :data:`ENVS`
    :return: the config's settings on that env
    """
    if env_id not in ENVS:
        raise KeyError(f"unknown env {env_id!r}; known: {sorted(ENVS)}")
    spec = ENVS[env_id]
    kind: AlgoKind
    if algo in NFQ_CONFIGS:
        kind, kwargs, source = "nfq", _per_env(NFQ_CONFIGS[algo], algo, env_id), "benchmarks/configs.py"
    elif algo in REFERENCE_CONFIGS:
        kind, kwargs, source = "reference", _per_env(REFERENCE_CONFIGS[algo], algo, env_id), "benchmarks/configs.py"
    elif algo == DQN_ZOO:
        kind, kwargs = "dqn", zoo_dqn_hyperparams(env_id)
        source = f"rl_zoo3 {importlib.metadata.version('rl_zoo3')} hyperparams/dqn.yml"
    else:
        raise KeyError(f"unknown algorithm config {algo!r}; known: {algorithm_names()}")
    budget = int(float(kwargs.pop("n_timesteps", spec.budget)))
    json.dumps(kwargs)  # fail early on values that cannot be recorded
    return ResolvedConfig(
        algo=algo,
        kind=kind,
        env_id=env_id,
        kwargs=kwargs,
        budget=budget,
        threshold=spec.threshold,
        eval_every=spec.eval_every,
        source=source,
    )
