"""On PYTHONPATH, makes Python behave as on a machine without PortAudio and JACK: importing
sounddevice or jack raises OSError, as both do when their C library is missing (the packages
themselves install from PyPI everywhere). Used by tests/test_bare_machine.py."""
import sys


class _Absent:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("sounddevice", "_sounddevice", "jack", "_jack"):
            raise OSError(f"{name}: library not found (PortAudio/JACK absent on this machine)")
        return None


sys.meta_path.insert(0, _Absent())
