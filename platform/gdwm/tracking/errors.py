"""The tracking package's error, in a module of its own: the backend raises it, and so does the write queue the
backend's module imports (``gdwm.tracking.writes``), with no import between the two."""


class TrackingError(RuntimeError):
    """The tracking store cannot be reached or its actor died; the message is one line naming it."""
