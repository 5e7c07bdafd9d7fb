#!/usr/bin/env bash
# Rebuild the three.js that `softgrasp view` inlines into its page, from the exact versions pinned in
# tools/three/package-lock.json (npm registry, integrity-checked by `npm ci`):
#   src/softgrasp/viz/static/three.min.js   three.js whole + its OrbitControls addon, one minified
#                                           script defining the global THREE (bundled by esbuild)
#   src/softgrasp/viz/static/three.LICENSE  three.js's licence (MIT)
# Run from anywhere: bash tools/vendor_three.sh   (needs Node.js >= 18 and npm)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
pkg="$here/three"
static="$here/../src/softgrasp/viz/static"
cd "$pkg"
npm ci --no-audit --no-fund --loglevel=error
three="$(node -p 'require("./node_modules/three/package.json").version')"
esbuild="$(node -p 'require("./node_modules/esbuild/package.json").version')"
./node_modules/.bin/esbuild entry.js --bundle --minify --format=iife --global-name=THREE \
  --target=es2020 --log-level=warning \
  --banner:js="/* three.js ${three} (npm three@${three}, MIT licence: three.LICENSE) with its OrbitControls addon, bundled by esbuild ${esbuild} from tools/three by tools/vendor_three.sh */" \
  --outfile="$static/three.min.js"
cp node_modules/three/LICENSE "$static/three.LICENSE"
rm -rf node_modules
sha256sum "$static/three.min.js" "$static/three.LICENSE"
