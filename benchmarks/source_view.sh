# Sourced by the GPU scripts, which run this source tree without installing it (the GPU machine has no package
# index). `source_view ROOT` prints a folder to put first on PYTHONPATH: a view of ROOT's package in which the
# top-level kernels/ is tlvg_warp.kernels, as pyproject's package-dir maps it when the package is installed.
source_view() {
  local root; root=$(cd "${1:-.}" && pwd)
  local view=/tmp/tlvg-view${root//\//_}
  rm -rf "$view"; mkdir -p "$view/tlvg_warp"
  ln -s "$root"/tlvg_warp/* "$view/tlvg_warp/"
  ln -s "$root/kernels" "$view/tlvg_warp/kernels"
  echo "$view"
}
