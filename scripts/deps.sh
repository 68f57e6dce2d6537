#!/usr/bin/env bash
# Installs what Arbor's tests and tools need on Debian/Ubuntu: the Vulkan loader, vulkaninfo,
# the Khronos validation layer, and glslang + SPIRV-Tools (the shader tests compile GLSL at test
# time). As root it uses apt-get; otherwise it says what to install.
set -euo pipefail
need=()
ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1 ' || need+=(libvulkan1)
command -v vulkaninfo >/dev/null 2>&1 || need+=(vulkan-tools)
ls /usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json >/dev/null 2>&1 || need+=(vulkan-validationlayers)
command -v glslangValidator >/dev/null 2>&1 || need+=(glslang-tools)
command -v spirv-opt >/dev/null 2>&1 || need+=(spirv-tools)
if [ ${#need[@]} -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq "${need[@]}" >/dev/null
else
  echo "Arbor needs these packages: ${need[*]}" >&2
  echo "Install them with: sudo apt-get install -y ${need[*]}" >&2
  exit 1
fi
