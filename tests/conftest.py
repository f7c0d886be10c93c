"""Imported by pytest before the test modules: ``import evgs`` first, so that this process's numpy and
torch run the pinned CPU code paths (evgs/cpu_dispatch.py), as every ``evgs`` command's do, and runs made
here repeat those made in a subprocess bit for bit."""

import evgs  # noqa: F401
