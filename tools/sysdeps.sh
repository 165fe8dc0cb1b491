#!/usr/bin/env bash
# The system libraries rtctl's audio path needs beyond PyPI, installed once by `make` (set-up step):
#   libportaudio2  PortAudio, which the sounddevice package loads (audio backend, `rtctl devices`)
#   jackd2         a real audio server; the hardware-in-the-loop tests start `jackd -d dummy`,
#                  and JACK-Client (`rtctl emulate audio`) loads the libjack it brings
# Installs them with apt-get when this user can (root, or password-less sudo); otherwise prints
# the command and carries on: without them the audio tests skip, saying what to install, and
# everything else works. Never fails the set-up.
set -u
PKGS="libportaudio2 jackd2"

missing=()
ldconfig -p 2>/dev/null | grep -q 'libportaudio\.so\.2' || missing+=(libportaudio2)
{ command -v jackd >/dev/null 2>&1 && ldconfig -p 2>/dev/null | grep -q 'libjack\.so\.0'; } || missing+=(jackd2)
[ ${#missing[@]} -eq 0 ] && exit 0

want="${missing[*]}"
if ! command -v apt-get >/dev/null 2>&1; then
  echo "setup: $want not found and this is not a Debian-like system: install PortAudio and JACK2 with" \
       "your package manager for the audio backend and its HIL tests (they skip without them)"
  exit 0
fi
if [ "$(id -u)" = 0 ]; then
  sudo=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  sudo=(sudo -n)
else
  echo "setup: $want missing (audio backend, HIL tests skip without them); install with:" \
       "sudo apt-get install $want"
  exit 0
fi
echo "setup: installing $want with apt-get (audio backend and its hardware-in-the-loop tests)"
log=$(mktemp)
if ! { "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
       "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $want; } \
     >"$log" 2>&1; then
  tail -n 5 "$log" | sed 's/^/  apt-get: /'
  echo "setup: apt-get install $want failed; the audio HIL tests will skip (see the test summary)"
fi
rm -f "$log"
exit 0
