"""A tracking store that can't be reached, said in one line naming it (credentials masked).

At connection a server or database that does not answer, or refuses the credentials, fails at once: MLflow's own
clients retry a database connection for about 100 s (with a multi-line warning each time) and an HTTP request for
minutes, which helps a store that blinks, not one that is down or a password that is wrong. Later, a call that fails
because the store went away (a refused connection, a timeout, a server error) becomes a ``TrackingError`` naming the
store and the call: the one line a stage's failure or the command's exit shows.
"""

from __future__ import annotations

import re
import urllib.error
import urllib.request

from gdwm.redact import redact

PROBE_TIMEOUT_S = 10.0
"""How long the first contact with a store may take before it counts as not answering."""
DATABASES = ("postgresql", "mysql", "mssql")
"""SQLAlchemy URIs MLflow stores runs in directly (besides sqlite, which is a file)."""


_CAUSES = (
    (re.compile(r"Connection refused", re.I), "connection refused"),
    (re.compile(r"too many (\d)\d\d error responses", re.I), "server errors (HTTP {0}xx) on every retry"),
    (re.compile(r"timed? ?out", re.I), "timed out"),
    (re.compile(r"Name or service not known|nodename nor servname", re.I), "unknown host"),
)


def _first_line(e: BaseException | str) -> str:
    """The cause in a few words where it is a known one (MLflow's REST client wraps it in a long urllib3 repr), else
    the error's first line; credentials masked."""
    text = str(e).strip()
    for pattern, words in _CAUSES:
        if m := pattern.search(text):
            return words.format(*m.groups())
    line = next((ln.strip() for ln in text.splitlines() if ln.strip()), type(e).__name__)
    return redact(line if len(line) <= 300 else line[:297] + "...")


def probe(uri: str) -> str | None:
    """Why the store at ``uri`` can't be used (one line naming it), or None when it answers (or is a local file)."""
    scheme = uri.split(":", 1)[0].split("+", 1)[0].lower()
    if scheme in ("http", "https"):
        try:
            with urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=PROBE_TIMEOUT_S):
                return None
        except urllib.error.HTTPError as e:  # it answers: what it says about credentials comes with the first call
            return None if e.code < 500 else f"MLflow server {redact(uri)} answers /health with HTTP {e.code}"
        except OSError as e:
            return f"no MLflow server answers at {redact(uri)} ({_first_line(getattr(e, 'reason', e))})"
    if scheme in DATABASES:
        import sqlalchemy
        from sqlalchemy.pool import NullPool

        args = {"connect_timeout": int(PROBE_TIMEOUT_S)} if scheme == "postgresql" else {}
        engine = sqlalchemy.create_engine(uri, poolclass=NullPool, connect_args=args)
        try:
            engine.connect().close()
        except sqlalchemy.exc.SQLAlchemyError as e:
            cause = e.orig if getattr(e, "orig", None) is not None else e
            return f"tracking database {redact(uri)} refused the connection: {_first_line(cause)}"
        finally:
            engine.dispose()
    return None


def unreachable(e: BaseException) -> bool:
    """Whether ``e`` says the store is gone or failing (connection refused, timeout, a server error, a database
    that dropped the connection), as opposed to a request the store refused on its merits."""
    from mlflow.exceptions import MlflowException

    if isinstance(e, MlflowException):
        return e.get_http_status_code() >= 500
    try:
        import sqlalchemy.exc

        if isinstance(e, sqlalchemy.exc.OperationalError | sqlalchemy.exc.InterfaceError):
            return True
    except ImportError:
        pass
    import requests

    return isinstance(e, requests.exceptions.ConnectionError | requests.exceptions.Timeout)


def failure_line(uri: str, call: str, e: BaseException) -> str:
    """``tracking store <uri> failed <call>: <cause>``."""
    return f"tracking store {redact(uri)} failed {call}: {_first_line(e)}"
