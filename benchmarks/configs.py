"""
What the benchmark runs: the environments (threshold, evaluation period) and the algorithm configs.

The NFQ configs are data: the named zoo-format YAML files of ``sb3_nfq/hyperparams/`` (:data:`NFQ_CONFIG_NAMES`, read
through :mod:`sb3_nfq.configs`). An entry's kwargs are passed to ``NFQ("MlpPolicy", env, seed=seed, **kwargs)``,
written as in the RL Zoo's YAML files: ``policy_kwargs`` may be a string such as
``"dict(net_arch=[256, 256], optimizer_class=th.optim.Adam)"`` (evaluated with ``th``, ``nn`` and ``dict`` in scope),
``learning_rate`` may be ``"lin_1e-3"`` (linear schedule), and three extra keys are understood: ``n_envs`` (training
envs, default 1), ``policy`` (default ``"MlpPolicy"``) and ``n_timesteps`` (the step budget on that env). The values
are plain data (numbers, strings, lists, dicts): they are hashed into the job key and stored in the results file.
Adding a config is adding a file; a changed config is a new file with a new name, never an edit.
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


@dataclass(frozen=True)
class EnvSpec:
    """
    :param threshold: "solved" when the mean return of ``N_EVAL_EPISODES`` greedy episodes reaches this
    :param eval_every: evaluate at the first round end (NFQ, reference) or rollout start (DQN) at or after each
        multiple of this many env steps
    """

    threshold: float
    eval_every: int = 1024


#: The four benchmark envs. Thresholds: gymnasium's ``reward_threshold`` of each env (CartPole's 475 is also the
#: book's criterion).
#: Evaluation periods: every 1024 steps (the textbook's round) where an evaluation is cheap. Acrobot's and
#: LunarLander's unsolved episodes run 500 and 1000 steps, so one evaluation plays up to 50k and 100k env steps there,
#: several times a textbook round's fit: every 2048 and 5120 steps.
ENVS: dict[str, EnvSpec] = {
    "CartPole-v1": EnvSpec(threshold=475.0),
    "Acrobot-v1": EnvSpec(threshold=-100.0, eval_every=2048),
    "MountainCar-v0": EnvSpec(threshold=-110.0),
    "LunarLander-v3": EnvSpec(threshold=200.0, eval_every=5120),
}

#: Greedy episodes per evaluation (learning curve, solve criterion and final score).
N_EVAL_EPISODES = 100

#: The NFQ configs the benchmark runs, in report order: sb3_nfq/hyperparams/<name>.yml, where each is described.
NFQ_CONFIG_NAMES = (
    "nfq-book",
    "nfq-tuned",
    "nfq-shared",
    "nfq-linear",
    "nfq-capped",
    "nfq-capped-10k",
    "nfq-capped-mse",
    "nfq-short-rounds",
    "nfq-short-rounds-64",
    "nfq-short-rounds-lr-lin-4e-3",
    "nfq-short-rounds-lr-lin-4e-3-huber",
    "nfq-short-rounds-lr-lin-4e-3-huber-10",
    "nfq-short-rounds-lr-lin-4e-3-huber-5",
    "nfq-front-loaded",
    "nfq-front-loaded-eps-0.01",
    "nfq-front-loaded-keep-best",
)

#: The config whose budget the reference gets: it runs the same textbook settings.
REFERENCE_BUDGET_OF = "nfq-book"

#: The plain-PyTorch reference (benchmarks/reference_nfq.py): kwargs for ``ReferenceNFQ``, and its budget
#: (:data:`REFERENCE_BUDGET_OF`'s).
REFERENCE_CONFIGS: dict[str, dict[str, Any]] = {"reference-nfq": {}}

#: SB3's DQN with the RL Zoo's tuned hyperparameters (rl_zoo3's hyperparams/dqn.yml), n_timesteps as the budget.
DQN_ZOO = "dqn-zoo"

#: Keys of the Zoo's YAML that change the env or the training loop, which the runner does not apply (``normalize``
#: it does: :func:`sb3_nfq.configs.vec_normalize_kwargs`). None is set for the four envs here (checked when read);
#: rather than half-support them, a config that sets one is refused.
ZOO_UNSUPPORTED_KEYS = (
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
    return [*NFQ_CONFIG_NAMES, *REFERENCE_CONFIGS, DQN_ZOO]


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
    if algo in NFQ_CONFIG_NAMES:
        kind, kwargs, source = "nfq", read_entry(algo, env_id), f"sb3_nfq/hyperparams/{algo}.yml"
    elif algo in REFERENCE_CONFIGS:
        kwargs = {**REFERENCE_CONFIGS[algo], "n_timesteps": read_entry(REFERENCE_BUDGET_OF, env_id)["n_timesteps"]}
        kind, source = "reference", "benchmarks/configs.py"
    elif algo == DQN_ZOO:
        kind, kwargs = "dqn", zoo_dqn_hyperparams(env_id)
        source = f"rl_zoo3 {importlib.metadata.version('rl_zoo3')} hyperparams/dqn.yml"
    else:
        raise KeyError(f"unknown algorithm config {algo!r}; known: {algorithm_names()}")
    budget = int(float(kwargs.pop("n_timesteps")))
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


#: benchmarks/README.md's markers around the env table.
ENV_TABLE_MARKERS = ("<!-- env-table:start (generated by python -m benchmarks.configs) -->", "<!-- env-table:end -->")


def env_table() -> str:
    """:return: the markdown table of the envs: threshold, evaluation period, and each config's budget there"""
    algos = [*NFQ_CONFIG_NAMES, DQN_ZOO]
    lines = [
        "| env | threshold | `eval_every` | " + " | ".join(f"budget: {algo}" for algo in algos) + " |",
        "|---|---|---|" + "---|" * len(algos),
    ]
    for env_id, spec in ENVS.items():
        budgets = " | ".join(f"{resolve(algo, env_id).budget:,}" for algo in algos)
        lines.append(f"| {env_id} | {spec.threshold:g} | {spec.eval_every:,} | {budgets} |")
    return "\n".join(lines)


if __name__ == "__main__":
    from benchmarks.readme_blocks import replace_block

    readme = Path(__file__).resolve().parent / "README.md"
    readme.write_text(replace_block(readme.read_text(), ENV_TABLE_MARKERS, env_table()))
    print(f"wrote the env table into {readme}")
