// Khronos glTF-Validator on one .glb/.gltf file: prints the validator's JSON report on stdout.
// Exit 0 when the report has no errors and no warnings, 1 when it has some, 2 when the file cannot be read.
// Usage: node tools/validate-gltf.mjs FILE
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";

const file = process.argv[2];
if (!file) {
  console.error("usage: node tools/validate-gltf.mjs FILE");
  process.exit(2);
}
let bytes;
try {
  bytes = new Uint8Array(await readFile(file));
} catch (err) {
  console.error(String(err));
  process.exit(2);
}
const report = await validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: 0, // report every issue
  externalResourceFunction: (uri) => readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))),
});
console.log(JSON.stringify(report, null, 1));
const { numErrors, numWarnings } = report.issues;
process.exit(numErrors + numWarnings > 0 ? 1 : 0);
