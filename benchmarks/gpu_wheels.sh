# Sourced by the GPU call scripts: installs the wheels in $1 (default .whl) when diffusers is missing, and puts
# them and the repository on PYTHONPATH. Returns 1 if the install fails.
if ! python3 -c "import diffusers" 2>/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "${1:-.whl}"/*.whl || return 1
    export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
fi
export PYTHONPATH=$PWD:${PYTHONPATH:-} TQDM_DISABLE=1 PYTHONUNBUFFERED=1
