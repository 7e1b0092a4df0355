"""XGBoost imported for loading and predicting with a booster, without scikit-learn.

Importing XGBoost imports scikit-learn (about 0.7 s on two cores) for its estimator classes alone
(``XGBRegressor`` and kin), which loading a booster, ``inplace_predict``, ``xgboost.train`` and
``xgboost.dask.train`` never use. A one-scan ``mpi-lidar correct`` would spend most of its start-up there
(docs/results/correction.md, "Start-up"). Where neither package is imported yet, XGBoost is imported with
scikit-learn hidden, as if it were not installed: XGBoost then builds its estimator classes on its own
placeholder bases. scikit-learn itself stays importable afterwards; only XGBoost's scikit-learn estimators of
this process lack scikit-learn's base classes (mpi-lidar uses none of them).
"""

from __future__ import annotations

import sys
from types import ModuleType


def import_xgboost() -> ModuleType:
    """The ``xgboost`` module, imported without scikit-learn unless one of the two is imported already."""
    if "xgboost" in sys.modules or "sklearn" in sys.modules:
        import xgboost

        return xgboost
    sys.modules["sklearn"] = None  # type: ignore[assignment]  # None in sys.modules makes `import sklearn` fail
    try:
        import xgboost
    except ImportError:  # an XGBoost that needs scikit-learn: import both as usual
        del sys.modules["sklearn"]
        for name in [name for name in sys.modules if name == "xgboost" or name.startswith("xgboost.")]:
            del sys.modules[name]
        import xgboost
    finally:
        if sys.modules.get("sklearn", 0) is None:
            del sys.modules["sklearn"]
    return xgboost
