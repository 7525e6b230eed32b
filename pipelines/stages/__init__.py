"""The GaussianDWM++ stages, registered through ``gdwm.stage`` and listed in ``conf/pipeline/gaussiandwm_pp.yaml``."""
