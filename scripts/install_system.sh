#!/usr/bin/env bash
# System libraries the simulators render with (run by scripts/install.sh; safe to re-run).
#   * libosmesa6: MuJoCo (MetaWorld, gymnasium MuJoCo, LIBERO's robosuite) renders camera images on
#     CPU through OSMesa.
#   * Mesa >= 23 Vulkan (mesa-vulkan-drivers, libvulkan1): SAPIEN (ManiSkill3) needs a Vulkan
#     device even for state observations; Debian 12 ships Mesa 22.3, which fails, so on bookworm
#     the packages come from Debian's bookworm-backports suite (Mesa 25.x).
#   * chromium: the headless browser the intervention web page's test drives through Playwright
#     (tests/integration/realworld/test_intervention_browser.py; `playwright install` is not needed).
# Without root or apt-get this prints what to install and exits 0: the reasoning stack does not
# need these, and the simulator tests skip with a message naming what is missing.
set -euo pipefail
if [ "${INFINIRL_SKIP_SYSTEM:-0}" = "1" ]; then exit 0; fi
mesa_version() { dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null | sed 's/^[0-9]*://' | cut -d. -f1; }
have_all() {
  dpkg-query -W -f='${Status}' libosmesa6 2>/dev/null | grep -q "ok installed" &&
  dpkg-query -W -f='${Status}' libvulkan1 2>/dev/null | grep -q "ok installed" &&
  [ "$(mesa_version || echo 0)" -ge 23 ] 2>/dev/null &&
  dpkg-query -W -f='${Status}' chromium 2>/dev/null | grep -q "ok installed"
}
if have_all; then exit 0; fi
if [ "$(id -u)" != "0" ] || ! command -v apt-get >/dev/null; then
  echo "install_system.sh: not root or no apt-get; for simulator rendering install libosmesa6 and" \
       "Mesa >= 23 Vulkan drivers (see docs/envs.md), and chromium for the browser test. Skipping." >&2
  exit 0
fi
codename=$(. /etc/os-release 2>/dev/null && echo "${VERSION_CODENAME:-}")
target=()
if [ "$codename" = "bookworm" ]; then
  src=/etc/apt/sources.list.d/bookworm-backports.sources
  if ! grep -rqs "bookworm-backports" /etc/apt/sources.list /etc/apt/sources.list.d/; then
    printf 'Types: deb\nURIs: http://deb.debian.org/debian\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' > "$src"
  fi
  target=(-t bookworm-backports)
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq "${target[@]}" libosmesa6 mesa-vulkan-drivers libvulkan1 >/dev/null
# From the release's own suites (with its security updates), not from backports.
apt-get install -y -qq chromium >/dev/null
echo "install_system.sh: installed libosmesa6 + Mesa $(mesa_version) Vulkan + $(dpkg-query -W -f='chromium ${Version}' chromium)"
