"""Every command of the pipeline, in one place (the outermost room: nothing else imports it).

| command | module | what it does |
|---|---|---|
| ``gopre-run`` | ``run`` | launch (or resume, plan, sync) one sweep (Hydra) |
| ``gopre-report`` | ``report`` | a sweep's tables, figures and paired statistics; ``--paper`` |
| ``gopre-view`` | ``view`` | an episode in the web 3D viewer |
| ``gopre-export`` | ``export`` | a job's model as PLY / compressed PLY / .splat / SPZ |
| ``gopre-eval`` | ``eval`` | any 3DGS PLY scored on a scene's test views |
| ``gopre-data`` | ``data`` | inspect a dataset folder, generate the default scene |

Each is also installed as ``pipeline-<name>``, the old name, kept as an alias for one release.
"""

from __future__ import annotations

import os
import sys


def command_name(name: str) -> str:
    """The name the user typed (``gopre-<name>`` or its alias ``pipeline-<name>``), for messages;
    ``gopre-<name>`` when called otherwise (tests, ``python -m``)."""
    typed = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return typed if typed in (f"gopre-{name}", f"pipeline-{name}") else f"gopre-{name}"


def unwritable(path, option: str, folder: bool = False) -> str | None:
    """Why the command could not write its output ``path`` (``folder``: a folder it fills, else a
    file), naming the option; checked before any work. None when it can."""
    from pipeline.interchange.layout import cannot_write
    problem = cannot_write(path, folder)
    return None if problem is None else f"{option} {path}: {problem}"


def alias_note(name: str) -> str:
    return (f"(Also installed as pipeline-{name}, the old name: an alias kept for one release; "
            f"use gopre-{name}.)")
