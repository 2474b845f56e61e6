# Sourced by the set-up scripts: `pip_install PIP ARGS...` runs `PIP install -q ARGS...` and shows what
# pip says except the messages these set-ups expect (each named below). A failed install still fails.
#  - "WARNING: Location ... is ignored": this machine's pip configuration lists package folders that
#    may not exist; pip skips them.
#  - setuptools' "Editable installation" notice (an editable install of prop_cli and prop_adapters uses
#    a meta path finder: folders named like them in the working directory take precedence).
PIP_EXPECTED="^WARNING: Location|BuildBackendWarning: Editable installation|^\s*!!\s*$|^\s*\*+\s*$|Please be careful with folders in your working directory|name as your package as they may take precedence|with strategy, WheelFile\(wheel_path|^\s*$"
# A dropped connection is retried, not fatal: CI once failed when a 530 MB torch wheel stopped at 275 MB
# six times in a row. pip resumes a download itself (PIP_RESUME_RETRIES, pip >= 25.1; older pips ignore
# it), and a whole install that still ends on a network error is run again, up to 3 times; any other
# failure fails at once.
PIP_NETWORK_ERROR="incomplete-download|Connection (interrupted|reset|aborted|broken)|Read timed out|ConnectTimeout|Temporary failure in name resolution|ProtocolError|IncompleteRead"
pip_install() {
  local pip=$1 out rc attempt
  shift
  for attempt in 1 2 3; do
    rc=0
    out=$(PIP_RESUME_RETRIES=${PIP_RESUME_RETRIES:-20} "$pip" install -q --disable-pip-version-check "$@" 2>&1) || rc=$?
    printf '%s\n' "$out" | grep -v -E "$PIP_EXPECTED" >&2 || true
    if [ "$rc" -eq 0 ] || ! printf '%s\n' "$out" | grep -q -E "$PIP_NETWORK_ERROR"; then
      return $rc
    fi
    echo "pip_install: network error (attempt $attempt of 3)" >&2
    sleep $((attempt * 10))
  done
  return $rc
}
