"""``gdwm compare``: comparison tables (terminal, Markdown, LaTeX, CSV) and an HTML report from MLflow runs.

``layout`` (schemas, columns) -> ``runs`` (rows and their trials from MLflow) and ``references`` (reported rows
copied from papers) -> ``samples`` (per-sample predictions and scorers) -> ``table`` (cells with uncertainty, from the
pure ``stats``; marks by the rule of ``marks``; the words of ``legend``; averages by ``rounding``) -> ``render`` /
``report``; ``command`` wires them for the CLI. Importing this package is cheap: it loads no MLflow or matplotlib.
"""
