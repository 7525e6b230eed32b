"""``gdwm compare``: comparison tables (terminal, Markdown, LaTeX, CSV) and an HTML report from MLflow runs.

``layout`` (schemas, columns) -> ``runs`` (rows from MLflow) -> ``table`` (marks) -> ``render`` / ``report``;
``command`` wires them for the CLI. Importing this package is cheap: it loads no MLflow or matplotlib.
"""
