"""The paper's extended and unscented Kalman filters (Bender et al., eq. 11-29), kept as baselines."""

from .ekf import run_ekf
from .ukf import run_ukf

__all__ = ["run_ekf", "run_ukf"]
