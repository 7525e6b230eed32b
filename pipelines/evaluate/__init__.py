"""Benchmark scoring of a trial: ``suites.score_predictions`` turns prediction rows into the
NuInteract, NuInstruct and OmniDrive metrics; ``text``, ``grounding`` and ``planning`` hold the metric functions.

Nothing is re-exported, so importing ``pipelines.evaluate.config`` stays light.
"""
