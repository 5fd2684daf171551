#!/usr/bin/env bash
# Installs into the project's venv with pip, saying how much disk it needs first and, if pip
# fails, how much was free where pip writes (the venv and the temporary folder), so that a
# full disk reads as one line instead of pip's "[Errno 28] No space left on device".
# Usage: scripts/pip_install.sh VENV NEED_MB LABEL PIP_ARGS...
#   NEED_MB: what this step adds to VENV, measured on a fresh clone (Python 3.11, x86_64,
#   2026-11-27): `.` 2.7 GB, `.[test]` 0.5 GB more, `.[train]` 0.8 GB more,
#   `.[notebooks]` 0.1-0.3 GB more. The Makefile, like this script, needs bash.
set -uo pipefail
venv=$1 need_mb=$2 label=$3
shift 3
free_mb() { df -Pm "$1" 2>/dev/null | awk 'NR == 2 { print $4 }'; }
tmp=${TMPDIR:-/tmp}
venv_free=$(free_mb "$venv")
if [ -n "$venv_free" ] && [ "$venv_free" -lt "$need_mb" ]; then
  echo "drake-rus: installing $label needs about $need_mb MB in $venv; only $venv_free MB" \
    "are free there. Free some space or set VENV=<a folder on a larger disk>." >&2
fi
"$venv/bin/python" -m pip install --quiet "$@"
status=$?
if [ "$status" -eq 0 ]; then
  exit 0
fi
venv_free=$(free_mb "$venv")
tmp_free=$(free_mb "$tmp")
echo "drake-rus: pip could not install $label (exit $status). It needs about $need_mb MB in" \
  "$venv (${venv_free:-?} MB free now) and room for the downloads in $tmp" \
  "(${tmp_free:-?} MB free now; TMPDIR sets it). Run 'make' again once fixed: it resumes." >&2
exit "$status"
