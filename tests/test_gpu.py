"""
NFQ on a CUDA device: what SB3's ``device="auto"`` gives a user with a GPU. Skipped where torch sees no GPU (CI).
"""

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env

from sb3_nfq import NFQ, KeepBestCallback
from tests.envs import random_cartpole_arrays
from tests.test_offline import dataset_from

pytestmark = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")

#: The variants whose fitting touches other code than the textbook's: the growing memory with lengthening rounds,
#: mini-batch epochs, targets fixed per iteration, Huber loss, a decaying step and a clipped gradient.
VARIANT: dict[str, Any] = {
    "memory": "growing",
    "train_freq": 128,
    "round_fraction": 0.5,
    "gradient_steps": 3,
    "batch_size": 64,
    "target_mode": "fixed_per_iteration",
    "loss": "huber",
    "learning_rate": lambda progress: 1e-3 * progress,
    "max_grad_norm": 10.0,
}


def _all_on(model: BaseAlgorithm, device_type: str) -> bool:
    return all(p.device.type == device_type for p in model.policy.parameters())


@pytest.mark.parametrize("kwargs", [{"train_freq": 256, "gradient_steps": 3}, VARIANT], ids=["textbook", "variant"])
def test_auto_device_trains_on_the_gpu_and_loads_on_the_cpu_with_the_same_q_values(
    tmp_path: Path, kwargs: dict[str, Any]
) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, **kwargs)
    assert model.device.type == "cuda" and _all_on(model, "cuda")
    before = [p.detach().clone() for p in model.policy.parameters()]

    model.learn(1024)

    assert model.num_timesteps == 1024 and _all_on(model, "cuda")
    assert any(not th.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
    obs = np.asarray(random_cartpole_arrays(5, seed=1)["obs"][:32])
    with th.no_grad():
        q_gpu = model.q_net(th.as_tensor(obs, device="cuda")).cpu()
    model.save(tmp_path / "gpu.zip", exclude=None)
    model.save_replay_buffer(tmp_path / "memory.pkl")

    loaded = NFQ.load(tmp_path / "gpu.zip", device="cpu", env=make_vec_env("CartPole-v1", n_envs=1, seed=2))
    assert _all_on(loaded, "cpu")
    with th.no_grad():
        th.testing.assert_close(loaded.q_net(th.as_tensor(obs)), q_gpu, rtol=1e-4, atol=1e-4)
    loaded.load_replay_buffer(tmp_path / "memory.pkl")
    loaded.learn(256, reset_num_timesteps=False)  # the GPU's memory goes on filling, and fits, on the CPU
    assert loaded.num_timesteps == 1280


def test_cpu_zip_loads_onto_the_gpu_and_predicts_the_same_actions(tmp_path: Path) -> None:
    model = NFQ("MlpPolicy", "CartPole-v1", seed=0, device="cpu", train_freq=256, gradient_steps=2)
    model.learn(512)
    model.save(tmp_path / "cpu.zip")
    obs = np.asarray(random_cartpole_arrays(10, seed=3)["obs"][:64])

    loaded = NFQ.load(tmp_path / "cpu.zip", device="cuda")

    assert _all_on(loaded, "cuda")
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_offline_fit_on_the_gpu_fits_every_transition() -> None:
    dataset = dataset_from(random_cartpole_arrays(20, seed=0))
    model = NFQ.for_dataset("MlpPolicy", dataset, gradient_steps=4, batch_size=128, seed=0)
    assert model.device.type == "cuda"
    seen: list[int] = []
    model.q_net.register_forward_hook(
        lambda _m, inputs, _o: seen.append(len(inputs[0])) if th.is_grad_enabled() else None
    )

    model.fit_offline(dataset)

    assert sum(seen) == 4 * len(dataset) and _all_on(model, "cuda")


@pytest.mark.parametrize("algo", [NFQ, DQN])
def test_keep_best_restores_weights_on_the_gpu(algo: type[NFQ] | type[DQN]) -> None:
    kwargs: dict[str, Any] = {"train_freq": 128, "gradient_steps": 2} if algo is NFQ else {"learning_starts": 128}
    model = algo("MlpPolicy", "CartPole-v1", seed=0, **kwargs)
    callback = KeepBestCallback()

    model.learn(2048, callback=callback)

    assert callback.best_weights is not None and _all_on(model, "cuda")
    for name, tensor in model.policy.state_dict().items():
        assert th.equal(tensor, callback.best_weights[name]), name
