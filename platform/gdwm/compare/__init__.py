"""``gdwm compare``: comparison tables (terminal, Markdown, LaTeX, CSV) and an HTML report from MLflow runs.

``layout`` (schemas, columns) -> ``runs`` (rows and their trials from MLflow) -> ``samples`` (per-sample
predictions and scorers) -> ``table`` (cells with uncertainty and marks, from the pure ``stats``) -> ``render`` /
``report``; ``command`` wires them for the CLI. Importing this package is cheap: it loads no MLflow or matplotlib.
"""
