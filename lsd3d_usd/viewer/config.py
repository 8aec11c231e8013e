"""`lsd3d-usd view`'s configuration tree (lsd3d_usd.configtree): how the viewer serves a scene."""
from __future__ import annotations

from dataclasses import dataclass

from lsd3d_usd.configtree import option


@dataclass
class ViewConfig:
    # the port's range is checked by the command, whose message names 0 = any free port
    port: int = option(8021, help="TCP port (0 = any free port)", flag="--port",
                       metavar="PORT")
    host: str = option("127.0.0.1", help="address to listen on (the default is this machine "
                                         "only)", flag="--host", metavar="HOST")
    allow_remote: bool = option(False, help="allow a --host other than loopback (prints a "
                                            "warning: anyone who can reach the port can read "
                                            "the scene)", flag="--allow-remote")
    open: bool = option(False, help="open the page in the default browser", flag="--open")
    quiet: bool = option(False, help="do not log requests", flag="--quiet")
    validate: bool = option(True, help="the background validation whose problems the page "
                                       "lists", negate="--no-validate")
