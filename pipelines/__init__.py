"""Stage implementations and data for gdwm (import ``pipelines``)."""
