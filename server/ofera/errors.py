"""The package's root error: every failure of ``ofera`` that is the caller's input (a file, an array, a name, a
setting) is an :class:`OferaError`.

Each concept keeps its own subclass next to it (``HeadModelError``, ``AvatarError``, ``LayoutError``, ``BDAError``,
...); they are also ``ValueError`` subclasses, so ``except ValueError`` keeps catching them. The wire protocol's
errors are the protocol package's own (``ofera_protocol.ProtocolError``): the protocol knows nothing of the server.
"""

from __future__ import annotations


class OferaError(Exception):
    """A user-facing failure of the ``ofera`` package; the message says what was wrong and what to do."""
