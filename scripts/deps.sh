#!/usr/bin/env bash
# Installs what Arbor's tests and tools need on Debian/Ubuntu: the Vulkan loader, vulkaninfo,
# the Khronos validation layer, glslang + SPIRV-Tools (the shader tests compile GLSL at test
# time), lavapipe and valgrind. As root it uses apt-get; otherwise it says what to install.
set -euo pipefail
need=()
ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1 ' || need+=(libvulkan1)
command -v vulkaninfo >/dev/null 2>&1 || need+=(vulkan-tools)
ls /usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json >/dev/null 2>&1 || need+=(vulkan-validationlayers)
command -v glslangValidator >/dev/null 2>&1 || need+=(glslang-tools)
command -v spirv-opt >/dev/null 2>&1 || need+=(spirv-tools)
# The compute and ray-query tests run every shader on lavapipe (Mesa's CPU driver) too, as a
# second driver. Ray queries need Mesa 25 (bookworm-backports on Debian 12; Debian 12's own
# 22.3 has none); where backports cannot be had, the ray-query comparisons skip, saying so.
lavapipe_has_ray_query() {
  local m
  m=$(ls /usr/share/vulkan/icd.d/lvp_icd*.json 2>/dev/null | head -1)
  [ -n "$m" ] || return 1
  local info
  info=$(VK_ICD_FILENAMES="$m" vulkaninfo 2>/dev/null || true)
  grep -q VK_KHR_ray_query <<<"$info"
}
lavapipe_has_ray_query || need+=(mesa-vulkan-drivers)
# tests/teardown.rs runs a create/build/destroy program under valgrind's leak checker.
command -v valgrind >/dev/null 2>&1 || need+=(valgrind)
if [ ${#need[@]} -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq "${need[@]}" >/dev/null
  if ! lavapipe_has_ray_query && grep -qs '^Suites: bookworm bookworm-updates$' /etc/apt/sources.list.d/debian.sources; then
    sed -i 's/^Suites: bookworm bookworm-updates$/Suites: bookworm bookworm-updates bookworm-backports/' \
      /etc/apt/sources.list.d/debian.sources
    if apt-get update -qq && apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers >/dev/null; then
      echo "lavapipe: Mesa from bookworm-backports (ray queries)"
    else
      echo "lavapipe: bookworm-backports unavailable; the ray-query comparisons with lavapipe will skip" >&2
    fi
  fi
else
  echo "Arbor needs these packages: ${need[*]}" >&2
  echo "Install them with: sudo apt-get install -y ${need[*]}" >&2
  exit 1
fi
