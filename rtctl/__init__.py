"""rtctl: drive tactile displays in a fixed-rate real-time loop.

Importing the package is cheap and needs no audio, serial or DAQ driver: every subpackage
imports its heavy or optional dependencies (sounddevice, pyserial, nidaqmx, cv2) only where
they are used.
"""

__version__ = "0.1.0"
