"""Parameter identification: the fit as parts.

`crank_jax.identify` is a documented namespace. The fit, the posterior, the
experiment design and the validation are at the front door (`crank_jax.fit`, ...); here
are the tools around them:

- `fitted_scene`: the scene a fit started from, with its estimates (what
  `crank-jax fit` writes as the fitted scene file); `save_fitted_scene` writes it (a fit
  that did not converge only when asked, marked in the file);
- `DEMO` and `demo_record`: the settings, scene and synthetic record of the demo
  experiment (`crank-jax demo`), for a script or test that fits what the demo fits;
- `FREE_NAMES`: every name `fit(free=...)` accepts; `regressor_start`: start values of the
  masses, inertias, k and c from the linear regressor form; `Profile`: a profile likelihood
  (`FitResult.profile`);
- residual diagnostics: `residual_diagnostics` and its `Diagnostics`; `hac_covariance`
  (a Newey-West covariance of correlated residuals); `widen_covariance` (white-noise
  variances as a floor under it); `robust_uncertainty` and its `RobustUncertainty`.
"""

from ..stats.diagnostics import (
    Diagnostics,
    RobustUncertainty,
    hac_covariance,
    residual_diagnostics,
    robust_uncertainty,
)
from ..stats.diagnostics import widen as widen_covariance
from .demo import DEMO, demo_record
from .fit import FREE_NAMES, regressor_start
from .fit_result import Profile
from .fitted import fitted_scene, save_fitted_scene

__all__ = ["fitted_scene", "save_fitted_scene", "FREE_NAMES", "regressor_start", "Profile",
           "residual_diagnostics", "Diagnostics",
           "hac_covariance", "widen_covariance", "robust_uncertainty", "RobustUncertainty",
           "DEMO", "demo_record"]
