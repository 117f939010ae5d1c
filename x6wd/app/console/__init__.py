"""The operator's web console served by the daemon (docs/console.md): the page in
``static/`` and its server in :mod:`x6wd.app.console.server`."""

from x6wd.app.console.server import ConsoleServer

__all__ = ["ConsoleServer"]
