"""The avatar package's error."""

from __future__ import annotations

from ..errors import OferaError


class AvatarError(OferaError, ValueError):
    """An avatar file or array set is invalid; the message says what and where."""
