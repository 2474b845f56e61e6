# Sourced by the set-up scripts: `pip_install PIP ARGS...` runs `PIP install -q ARGS...` and shows what
# pip says except the messages these set-ups expect (each named below). A failed install still fails.
#  - "WARNING: Location ... is ignored": this machine's pip configuration lists package folders that
#    may not exist; pip skips them.
#  - setuptools' "Editable installation" notice (an editable install of prop_cli and prop_adapters uses
#    a meta path finder: folders named like them in the working directory take precedence).
PIP_EXPECTED="^WARNING: Location|BuildBackendWarning: Editable installation|^\s*!!\s*$|^\s*\*+\s*$|Please be careful with folders in your working directory|name as your package as they may take precedence|with strategy, WheelFile\(wheel_path|^\s*$"
pip_install() {
  local pip=$1 out rc=0
  shift
  out=$("$pip" install -q --disable-pip-version-check "$@" 2>&1) || rc=$?
  printf '%s\n' "$out" | grep -v -E "$PIP_EXPECTED" >&2 || true
  return $rc
}
