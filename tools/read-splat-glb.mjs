// three.js's glTF loader with its KHR_gaussian_splatting plugin on one .glb: prints what it read as JSON
// ({reader, splats, count, min, max, covariances, colors}: the first `n` splats' covariance (xx, xy, xz, yy, yz, zz,
// in the file's axes) and RGBA bytes, as three computes them from SCALE, ROTATION, SH_DEGREE_0_COEF_0, OPACITY).
// Exit 0 when read, 1 when the loader fails, 2 when the file cannot be read.
// Usage: node tools/read-splat-glb.mjs FILE [n]
import { readFile } from "node:fs/promises";
import { REVISION } from "three";
import { GLTFGaussianSplatLoaderExtension } from "three/addons/loaders/GLTFGaussianSplatLoaderExtension.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const [file, first = "8"] = process.argv.slice(2);
if (!file) {
  console.error("usage: node tools/read-splat-glb.mjs FILE [n]");
  process.exit(2);
}
let bytes;
try {
  bytes = await readFile(file);
} catch (err) {
  console.error(String(err));
  process.exit(2);
}
const loader = new GLTFLoader();
loader.register((parser) => new GLTFGaussianSplatLoaderExtension(parser));
const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
try {
  loader.parse(
  buffer,
  "",
  (gltf) => {
    const splats = [];
    gltf.scene.traverse((o) => o.isGaussianSplat && splats.push(o));
    if (splats.length !== 1) {
      console.error(`expected one Gaussian splat object, found ${splats.length}`);
      process.exit(1);
    }
    const g = splats[0].splatGeometry;
    const n = Math.min(Number(first), g.attributes.position.count);
    console.log(
      JSON.stringify({
        reader: `three.js r${REVISION} GLTFLoader + GLTFGaussianSplatLoaderExtension`,
        splats: splats.length,
        count: g.attributes.position.count,
        min: g.boundingBox.min.toArray(),
        max: g.boundingBox.max.toArray(),
        covariances: Array.from(g.attributes.covariance.array.slice(0, 6 * n)),
        colors: Array.from(g.attributes.color.array.slice(0, 4 * n)),
      }),
    );
  },
  (err) => {
    console.error(String(err));
    process.exit(1);
  },
  );
} catch (err) {
  console.error(String(err));
  process.exit(1);
}
