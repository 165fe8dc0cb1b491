#!/usr/bin/env bash
# The system packages rtctl uses beyond PyPI, installed once by `make` (set-up step):
#   libportaudio2  PortAudio, which the sounddevice package loads (audio backend, `rtctl devices`)
#   jackd2         a real audio server; the hardware-in-the-loop tests start `jackd -d dummy`,
#                  and JACK-Client (`rtctl emulate audio`) loads the libjack it brings
#   rt-tests       cyclictest, what `rtctl bench realtime` compares the paced loop with
#   stress-ng      the load of `rtctl bench realtime --load N`
# Installs them with apt-get when this user can (root, or password-less sudo); otherwise prints
# the command and carries on: without them the audio tests skip, saying what to install, the
# bench runs the loop alone and says so, and everything else works. Never fails the set-up.
set -u

missing=()
ldconfig -p 2>/dev/null | grep -q 'libportaudio\.so\.2' || missing+=(libportaudio2)
{ command -v jackd >/dev/null 2>&1 && ldconfig -p 2>/dev/null | grep -q 'libjack\.so\.0'; } || missing+=(jackd2)
command -v cyclictest >/dev/null 2>&1 || missing+=(rt-tests)
command -v stress-ng >/dev/null 2>&1 || missing+=(stress-ng)
[ ${#missing[@]} -eq 0 ] && exit 0

want="${missing[*]}"
if ! command -v apt-get >/dev/null 2>&1; then
  echo "setup: $want not found and this is not a Debian-like system: install them with your package" \
       "manager (PortAudio and JACK2: the audio backend and its HIL tests, which skip without them;" \
       "cyclictest and stress-ng: rtctl bench realtime)"
  exit 0
fi
if [ "$(id -u)" = 0 ]; then
  sudo=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  sudo=(sudo -n)
else
  echo "setup: $want missing (audio backend and its HIL tests, rtctl bench realtime); install with:" \
       "sudo apt-get install $want"
  exit 0
fi
echo "setup: installing $want with apt-get (audio backend and its hardware-in-the-loop tests, rtctl bench realtime)"
log=$(mktemp)
apt() { "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get "$@" >>"$log" 2>&1; }
install() { apt install -y -qq --no-install-recommends "$@"; }
failed=""
if ! apt update -qq; then
  failed="$want"
elif ! install "${missing[@]}"; then
  # one package this archive lacks must not keep the others out: each on its own
  for p in "${missing[@]}"; do install "$p" || failed="$failed $p"; done
fi
if [ -n "$failed" ]; then
  tail -n 5 "$log" | sed 's/^/  apt-get: /'
  echo "setup: apt-get install ${failed# } failed; without PortAudio/JACK the audio HIL tests skip (see the" \
       "test summary), without cyclictest/stress-ng rtctl bench realtime runs the loop alone"
fi
rm -f "$log"
exit 0
