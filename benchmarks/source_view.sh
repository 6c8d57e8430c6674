# Sourced by the GPU scripts, which run this source tree without installing it (the GPU machine has no package
# index). `source_view ROOT` prints a folder to put first on PYTHONPATH: a view of ROOT's package in which the
# top-level kernels/ is tlvg_warp.kernels, as pyproject's package-dir maps it when the package is installed.
# Links are only added, never removed: a later call (e.g. `PART=wait`) must not pull modules from under the
# processes an earlier call left running.
source_view() {
  local root; root=$(cd "${1:-.}" && pwd)
  local view=/tmp/tlvg-view${root//\//_} f
  mkdir -p "$view/tlvg_warp"
  for f in "$root"/tlvg_warp/*; do
    [ -e "$view/tlvg_warp/${f##*/}" ] || ln -s "$f" "$view/tlvg_warp/"
  done
  [ -e "$view/tlvg_warp/kernels" ] || ln -s "$root/kernels" "$view/tlvg_warp/kernels"
  # `python3 -m tlvg_warp` puts the working directory ahead of PYTHONPATH, so it imports ROOT's own package: where
  # that cannot find tlvg_warp.kernels (a copy of the tree that was never installed), kernels/ is linked into it
  # (ignored by git)
  if [ ! -e "$root/tlvg_warp/kernels" ] && ! (cd "$root" && python3 -c "import importlib.util as u, sys; sys.exit(u.find_spec('tlvg_warp.kernels') is None)" 2>/dev/null); then
    ln -s ../kernels "$root/tlvg_warp/kernels"
  fi
  echo "$view"
}
