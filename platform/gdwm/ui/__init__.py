"""``gdwm ui``: gdwm's own dashboard over the configured tracking store.

Pages: launches (sweeps, runs, regressions, newest first, filtered by name and state), a sweep (live trials x stages
grid with one-line causes and an ETA, the paper-layout table computed by ``gdwm compare``'s own code, plots with
intervals, factor effects, learning curves, parallel coordinates, downloads), a trial (config diff, stages with how
and why they ran, logs, artifacts), regressions (each checked metric over time with its baseline and band, every
verdict) and the zoo. Every page links to the MLflow run it shows where an MLflow UI is known (``--mlflow``).

Built on Starlette + Jinja2 served by uvicorn (already installed as MLflow's own server stack: no new web framework,
server-rendered pages, plain HTTP polling for live parts) and Plotly's Python package, whose ``plotly.min.js`` is
served from the package (no CDN: clusters are often offline). Modules: ``store`` (read-only MLflow client),
``live`` (progress snapshot + events), ``pages`` (what each page reads), ``tables`` / ``worker`` (the table, in a
process of its own, kept per set of finished trials), ``tablehtml``, ``effects``, ``charts``, ``app``, ``serve``.
"""
