#!/bin/sh
# Can PYTHON make anisdf's virtual environment? Run by `make` before it creates .venv:
#     sh scripts/check_python.sh [PYTHON]        (default python3)
# When PYTHON is missing, does not run, is older than pyproject.toml's requires-python or lacks the venv module
# (ensurepip), prints what to do as one line on stdout (the Makefile stops with it) and exits 1. When the fast CPU
# kernel cannot be built (no C++ compiler, no Python headers) it warns on stderr and exits 0. The minimum version is
# read from pyproject.toml, never written here.
py=${1:-python3}
root=$(cd "$(dirname "$0")/.." && pwd)

need=$(sed -n 's/^requires-python *= *"[^0-9]*\([0-9][0-9.]*\)".*/\1/p' "$root/pyproject.toml")
if [ -z "$need" ]; then
    echo "no requires-python = \">=X.Y\" in $root/pyproject.toml"
    exit 1
fi
need_major=${need%%.*}
need_minor=${need#*.}
need_minor=${need_minor%%.*}

# A newer python3.N on PATH that runs, to suggest when PYTHON is too old or lacks venv.
suggest() {
    n=30
    while [ "$n" -ge "$need_minor" ]; do
        cand="python$need_major.$n"
        if [ "$cand" != "$py" ] && command -v "$cand" >/dev/null 2>&1 \
            && "$cand" -c "import ensurepip" >/dev/null 2>&1; then
            echo "$cand"
            return
        fi
        n=$((n - 1))
    done
}

if ! command -v "$py" >/dev/null 2>&1; then
    other=$(suggest)
    echo "$py not found; anisdf needs Python >= $need: install it${other:+, or run make PYTHON=$other}"
    exit 1
fi
if ! have=$("$py" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>&1); then
    other=$(suggest)
    echo "$py does not run ($(echo "$have" | head -n 1)); anisdf needs Python >= $need:" \
        "${other:+run make PYTHON=$other, or }install it"
    exit 1
fi
if ! "$py" -c "import sys; sys.exit(sys.version_info[:2] < ($need_major, $need_minor))" >/dev/null 2>&1; then
    other=$(suggest)
    echo "$py is $have; anisdf needs Python >= $need: install it, or run make PYTHON=${other:-python$need_major.X}"
    exit 1
fi
if ! "$py" -c "import venv, ensurepip" >/dev/null 2>&1; then
    case "${py##*/}" in
        python3) pkg=python3-venv ;;
        *) pkg="python$have-venv" ;;
    esac
    echo "$py has no venv module: apt-get install $pkg"
    exit 1
fi

cxx=${CXX:-c++}  # the compiler torch's extension builder calls
if ! command -v "$cxx" >/dev/null 2>&1; then
    echo "warning: the fast CPU kernel needs a C++ compiler (apt-get install g++); without it training uses" \
        "the slower PyTorch encoding" >&2
elif ! "$py" -c "import os, sys, sysconfig
sys.exit(not os.path.isfile(os.path.join(sysconfig.get_paths()['include'], 'Python.h')))" >/dev/null 2>&1; then
    case "${py##*/}" in
        python3) dev=python3-dev ;;
        *) dev="python$have-dev" ;;
    esac
    echo "warning: the fast CPU kernel needs Python's headers (apt-get install $dev); without them training" \
        "uses the slower PyTorch encoding" >&2
fi
exit 0
