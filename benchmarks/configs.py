"""
What the benchmark runs: the envs (threshold, evaluation period), the seeds, and the algorithm configs (NFQ: the
zoo-format files of ``benchmarks/hyperparams/``, never edited once run; the peers: the installed ``rl_zoo3``'s DQN
and QR-DQN entries; a ``-keep-best`` name runs its base config with ``sb3_nfq.KeepBestCallback``).
"""

import importlib.metadata
import importlib.util
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from sb3_nfq.configs import read_entry

AlgoKind = Literal["nfq", "reference", "dqn", "qrdqn"]
HYPERPARAMS_DIR = Path(__file__).resolve().parent / "hyperparams"


@dataclass(frozen=True)
class EnvSpec:
    """
    :param threshold: "solved" when the mean return of ``N_EVAL_EPISODES`` greedy episodes reaches this
    :param eval_every: evaluate at the first round end (NFQ, reference) or rollout start (DQN) at or after each
        multiple of this many env steps
    """

    threshold: float
    eval_every: int = 1024


#: Thresholds: gymnasium's ``reward_threshold`` (CartPole's 475 is also the book's). One evaluation of Acrobot and
#: LunarLander plays up to 50k and 100k env steps, several times a textbook round's fit: evaluated less often there.
ENVS: dict[str, EnvSpec] = {
    "CartPole-v1": EnvSpec(threshold=475.0),
    "Acrobot-v1": EnvSpec(threshold=-100.0, eval_every=2048),
    "MountainCar-v0": EnvSpec(threshold=-110.0),
    "LunarLander-v3": EnvSpec(threshold=200.0, eval_every=5120),
}

#: Greedy episodes per evaluation (learning curve, solve criterion and final score).
N_EVAL_EPISODES = 100
#: The seeds every measured row of the report runs on.
SEEDS = tuple(range(5))
#: Seeds no config was chosen on, to measure a chosen config again without selection bias.
HELD_OUT_SEEDS = tuple(range(5, 15))

#: The NFQ configs still measured (benchmarks/hyperparams/<name>.yml), in report order.
NFQ_CONFIG_NAMES = (
    "nfq-book",
    "nfq-front-loaded-batch-128",
    "nfq-front-loaded-batch-128-k12-first-termination",
    "nfq-short-rounds-lr-lin-4e-3-huber-5-ez-2-iteration-10k-n-step-3",
    "nfq-short-rounds-lr-lin-4e-3-huber-5-n-step-3",
    "nfq-short-rounds-lr-lin-4e-3-huber-5-n-step-3-critics-2-ucb-3",
    "nfq-short-rounds-lr-lin-4e-3-huber-5-n-step-3-critics-2-ucb-3-iteration-10k",
    "nfq-LunarLander-v3-30k-trial-119",
)
#: The benchmark config each entry of the shipped sb3_nfq/hyperparams/nfq.yml was measured as.
SHIPPED: dict[str, str] = {
    "CartPole-v1": "nfq-front-loaded-batch-128-keep-best",
    "Acrobot-v1": "nfq-front-loaded-batch-128-k12-first-termination-keep-best",
    "MountainCar-v0": "nfq-short-rounds-lr-lin-4e-3-huber-5-ez-2-iteration-10k-n-step-3",
    "LunarLander-v3": "nfq-LunarLander-v3-30k-trial-119",
    "default": "nfq-short-rounds-lr-lin-4e-3-huber-5-ez-2-iteration-10k-n-step-3",
}
#: The one config run unchanged on every env: the shipped file's entry for a new problem.
ONE_CONFIG = SHIPPED["default"]
#: The plain-PyTorch reference (benchmarks/reference_nfq.py), with nfq-book's budget: the same textbook settings.
REFERENCE = "reference-nfq"
#: The peers: name -> (kind, the rl_zoo3 hyperparameters file).
ZOO_PEERS: dict[str, tuple[AlgoKind, str]] = {"dqn-zoo": ("dqn", "dqn.yml"), "qrdqn-zoo": ("qrdqn", "qrdqn.yml")}
#: The name suffix that runs the config before it with sb3_nfq.KeepBestCallback's defaults (recorded as
#: ``keep_best: true``).
KEEP_BEST_SUFFIX = "-keep-best"
#: Keys of the Zoo's format that change the env or the training loop, which the runner does not apply (no config sets
#: one on the four envs): an entry that sets one is refused rather than half-applied.
NOT_APPLIED = ("normalize", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback", "env_kwargs", "monitor_kwargs")


@dataclass(frozen=True)
class ResolvedConfig:
    """
    One algorithm's settings on one env.

    :param algo: config name
    :param kind: which trainer runs it
    :param env_id: gymnasium env id
    :param kwargs: constructor kwargs as plain data (``n_envs``, ``policy``, ``keep_best`` kept; no budget)
    :param budget: env-step budget
    :param source: where the values come from (for the record)
    """

    algo: str
    kind: AlgoKind
    env_id: str
    kwargs: dict[str, Any]
    budget: int
    source: str


def algorithm_names() -> list[str]:
    """:return: every algorithm config the runner knows, in report order"""
    nfq, peers = (
        [name + suffix for name in names for suffix in ("", KEEP_BEST_SUFFIX)]
        for names in (NFQ_CONFIG_NAMES, ZOO_PEERS)
    )
    return [*nfq, REFERENCE, *peers]


def keep_best_suffix(algo: str) -> str:
    """:return: :data:`KEEP_BEST_SUFFIX` if the name ends with it, else ``""``"""
    return KEEP_BEST_SUFFIX if algo.endswith(KEEP_BEST_SUFFIX) else ""


def peers_of(algo: str) -> list[str]:
    """:return: the peers an NFQ config is compared with, selected alike (a ``-keep-best`` config: their -keep-best)"""
    return [peer + keep_best_suffix(algo) for peer in ZOO_PEERS]


def zoo_file(name: str) -> Path:
    """:return: the installed rl_zoo3 package's ``hyperparams/<name>`` (found without importing rl_zoo3)"""
    spec = importlib.util.find_spec("rl_zoo3")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("the zoo peers need rl_zoo3: the zoo extra, pip install '.[zoo]'")
    return Path(next(iter(spec.submodule_search_locations))) / "hyperparams" / name


def resolve(algo: str, env_id: str) -> ResolvedConfig:
    """
    :param algo: an algorithm config name (see :func:`algorithm_names`)
    :param env_id: one of :data:`ENVS`
    :return: the config's settings on that env
    """
    if env_id not in ENVS:
        raise KeyError(f"unknown env {env_id!r}; known: {sorted(ENVS)}")
    suffix = keep_best_suffix(algo)
    base = algo.removesuffix(suffix)
    kind: AlgoKind
    if base in NFQ_CONFIG_NAMES:
        kind, source = "nfq", f"benchmarks/hyperparams/{base}.yml"
        kwargs = read_entry(env_id, HYPERPARAMS_DIR / f"{base}.yml")
    elif algo == REFERENCE:
        kind, source = "reference", "benchmarks/reference_nfq.py"
        kwargs = {"n_timesteps": read_entry(env_id, HYPERPARAMS_DIR / "nfq-book.yml")["n_timesteps"]}
    elif base in ZOO_PEERS:
        kind, file_name = ZOO_PEERS[base]
        kwargs = read_entry(env_id, zoo_file(file_name))
        source = f"rl_zoo3 {importlib.metadata.version('rl_zoo3')} hyperparams/{file_name}"
    else:
        raise KeyError(f"unknown algorithm config {algo!r}; known: {algorithm_names()}")
    if suffix:
        kwargs["keep_best"] = True
    if present := [key for key in NOT_APPLIED if key in kwargs]:
        raise NotImplementedError(f"{source}'s entry for {env_id} sets {present}, which the runner does not apply")
    budget = int(float(kwargs.pop("n_timesteps")))
    json.dumps(kwargs)  # fail early on values that cannot be recorded
    return ResolvedConfig(algo, kind, env_id, kwargs, budget, source)
