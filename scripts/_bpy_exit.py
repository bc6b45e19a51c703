"""Leave a process that imported bpy with a given exit code, past bpy's own exit bugs.

bpy 4.2.x segfaults at interpreter exit (``bpy_class_free``) once a class with a ``get=``
property callback was registered: exit code 139 after the work succeeded.  bpy 4.5.x can hang
at exit, a bpy thread waiting on a condition variable that is being destroyed.  Both happen
after every line of our own code ran, so the tests (tests/conftest.py), the install round-trip
and the demo leave with their own result through ``os._exit`` instead, once their output is
flushed.  The code passed is always the caller's own result: a failure still exits non-zero.
"""

import os
import sys


def exit_past_bpy(code: int) -> None:
    """Exit with ``code`` now when bpy was imported; otherwise return (the caller exits normally)."""
    if "bpy" in sys.modules:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(int(code))
