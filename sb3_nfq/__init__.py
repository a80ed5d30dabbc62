"""sb3-nfq: Neural Fitted Q-Iteration (NFQ) as a Stable-Baselines3 algorithm."""

from sb3_nfq.callbacks import BookCriterion, KeepBestCallback, StopTrainingOnBookCriterion
from sb3_nfq.fitting import NFQDivergenceError
from sb3_nfq.nfq import NFQ
from sb3_nfq.offline import TransitionDataset
from sb3_nfq.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, NFQPolicy

__version__ = "0.1.0"

__all__ = [
    "NFQ",
    "BookCriterion",
    "CnnPolicy",
    "KeepBestCallback",
    "MlpPolicy",
    "MultiInputPolicy",
    "NFQDivergenceError",
    "NFQPolicy",
    "StopTrainingOnBookCriterion",
    "TransitionDataset",
    "__version__",
]
