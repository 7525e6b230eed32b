"""gdwm: the experiment platform for Gaussian driving world models.

Lives in ``platform/gdwm``; ``platform/`` itself is not a package, so the standard
library's ``platform`` module (imported by torch, ray and mlflow) is never shadowed.
"""

__version__ = "0.1.0"
