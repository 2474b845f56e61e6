# Sourced by the set-up and test scripts: `say` (one line to stderr before each long step), `timed NAME`
# (at exit, "NAME: done in N s" or "NAME: failed after N s") and `pip_install PIP ARGS...`.
#
# pip_install runs `PIP install ARGS...` and streams what pip says to stderr as it says it (a download's
# size before it starts, a build's "still running" each minute), except the messages these set-ups expect
# (PIP_EXPECTED) and pip's routine progress notes (PIP_ROUTINE). A failed install still fails.
#  - "WARNING: Location ... is ignored": this machine's pip configuration lists package folders that
#    may not exist; pip skips them.
#  - setuptools' "Editable installation" notice (an editable install of prop_cli and prop_adapters uses
#    a meta path finder: folders named like them in the working directory take precedence).
PIP_EXPECTED="^WARNING: Location|BuildBackendWarning: Editable installation|^\s*!!\s*$|^\s*\*+\s*$|Please be careful with folders in your working directory|name as your package as they may take precedence|with strategy, WheelFile\(wheel_path|^\s*$"
# One line per package that is already there, found, unpacked or uninstalled: hundreds for LeRobot's
# environment, and none of them is slow. Downloads under 10 MB are quick too; larger ones are shown.
PIP_ROUTINE="^\s*(Looking in (indexes|links):|Requirement already satisfied:|Collecting |Processing |Obtaining |Using cached |File was already downloaded|Saved |Stored in directory:|Created wheel for |Successfully built |Building wheels for collected packages:|Attempting uninstall:|Found existing installation:|Uninstalling |Successfully uninstalled |\[notice\]|Installing build dependencies|Installing backend dependencies|Checking if build backend|Getting requirements to build|Preparing (editable )?metadata|Building editable for )|^\s*Downloading .*\(([0-9.]+ (bytes|kB)|[0-9](\.[0-9]+)? MB)\)$"
# A dropped connection is retried, not fatal: CI once failed when a 530 MB torch wheel stopped at 275 MB
# six times in a row. pip resumes a download itself (PIP_RESUME_RETRIES, pip >= 25.1; older pips ignore
# it), and a whole install that still ends on a network error is run again, up to 3 times, after
# PIP_RETRY_DELAY x attempt seconds (default 10); any other failure fails at once.
PIP_NETWORK_ERROR="incomplete-download|Connection (interrupted|reset|aborted|broken)|Read timed out|ConnectTimeout|Temporary failure in name resolution|ProtocolError|IncompleteRead"

say() { echo "$*" >&2; }

timed() {
  _timed_name=$1
  SECONDS=0
  trap '_timed_rc=$?; if [ "$_timed_rc" -eq 0 ]; then say "$_timed_name: done in $SECONDS s"; else say "$_timed_name: failed after $SECONDS s"; fi; exit "$_timed_rc"' EXIT
}

pip_install() {
  local pip=$1 log rc attempt line
  shift
  log=$(mktemp)
  for attempt in 1 2 3; do
    rm -f "$log.rc"
    # pip's progress bar draws only on a terminal (here its output goes through grep), so it is off; each
    # line reaches stderr when pip writes it (grep --line-buffered), and the log keeps them all for the
    # network-error check. The `||` keeps `set -e` from stopping here: pip's status goes through $log.rc.
    { PIP_RESUME_RETRIES=${PIP_RESUME_RETRIES:-20} PYTHONUNBUFFERED=1 \
        "$pip" install --disable-pip-version-check --progress-bar off "$@" 2>&1 || echo "$?" >"$log.rc"; } \
      | tee "$log" | { grep --line-buffered -v -E "$PIP_EXPECTED|$PIP_ROUTINE" || true; } \
      | while IFS= read -r line; do printf '  %s\n' "$line" >&2; done
    rc=$(cat "$log.rc" 2>/dev/null || echo 0)
    if [ "$rc" -eq 0 ] || ! grep -q -E "$PIP_NETWORK_ERROR" "$log"; then
      rm -f "$log" "$log.rc"
      return "$rc"
    fi
    say "pip_install: network error (attempt $attempt of 3)"
    sleep $((attempt * ${PIP_RETRY_DELAY:-10}))
  done
  rm -f "$log" "$log.rc"
  return "$rc"
}
