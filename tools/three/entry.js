// The one file that `softgrasp view` inlines: three.js whole and its OrbitControls addon, as the
// global `THREE` (tools/vendor_three.sh bundles it into src/softgrasp/viz/static/three.min.js).
export * from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
