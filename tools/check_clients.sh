#!/usr/bin/env bash
# Generated clients of the contract (openapi.yaml) keep the binary responses and accept the
# README request, with no edits to what the generators write:
#   1. TypeScript: openapi-typescript 7 types; a client.ts (the README request, its meshopt
#      variant and the contract's DrapeRequest / BodyFitRequest examples as typed literals, the 200s
#      of POST /v1/drape and GET /v1/jobs/{job_id}/result checked at the type level) passes
#      `tsc --noEmit --strict`.
#   2. Python: openapi-python-client (in a throwaway venv) with tools/openapi-python-client.yaml
#      generates without a warning; POST /v1/drape and the job result return bytes (types.File)
#      through the generated functions (an httpx.MockTransport answers: no network); the README
#      request and the contract's examples go through the generated models unchanged
#      (from_dict(...).to_dict() == the JSON).
# Downloads from the npm registry (npx) and PyPI (pip); writes only under a temp dir
# (KEEP_TMP=1 keeps it). Usage: tools/check_clients.sh   (tests/test_generated_clients.py runs it
# when TRYON_CHECK_CLIENTS=1)
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
SPEC=${CHECK_CLIENTS_SPEC:-$ROOT/openapi.yaml}  # (another contract or config: to see the checks fail)
PY_CONFIG=${CHECK_CLIENTS_PY_CONFIG:-$ROOT/tools/openapi-python-client.yaml}
PYTHON=${PYTHON:-python3}
TMP=$(mktemp -d "${TMPDIR:-/tmp}/check_clients.XXXXXX")
if [[ ${KEEP_TMP:-0} == 1 ]]; then echo "temp dir (kept): $TMP"; else trap 'rm -rf "$TMP"' EXIT; fi

say() { printf '\n== %s\n' "$*"; }

# The README request (README.md, "Try it") and its compressed variant (the issue's acceptance).
README_REQUEST='{"body": {"phenotypes": {"gender": 0.5, "age": 0.8, "weight": 0.5, "height": 0.5}},
 "motion": {"type": "clip", "clip": "walk", "duration_s": 2.0}, "garments": [{"id": "tshirt"}], "format": "glb"}'

say "throwaway venv: openapi-python-client (with httpx, ruamel.yaml, ruff)"
"$PYTHON" -m venv "$TMP/venv"
VENV=$TMP/venv/bin
"$VENV/pip" install --quiet --disable-pip-version-check 'openapi-python-client==0.29.*' 2>&1 | grep -v '^WARNING: Location' || true
"$VENV/openapi-python-client" --version

# The contract's request examples, by schema: {"DrapeRequest": {"walk_tshirt": {...}}, "BodyFitRequest": {...}}
"$VENV/python" - "$SPEC" "$README_REQUEST" >"$TMP/examples.json" <<'EOF'
import json, sys
from ruamel.yaml import YAML
spec = YAML(typ="safe").load(open(sys.argv[1]))
out = {"DrapeRequest": {"readme": json.loads(sys.argv[2])}, "BodyFitRequest": {}}
out["DrapeRequest"]["readme_meshopt"] = {**out["DrapeRequest"]["readme"], "options": {"compression": "meshopt"}}
for path, item in spec["paths"].items():
    for method, op in item.items():
        media = (op.get("requestBody") or {}).get("content", {}).get("application/json", {})
        name = media.get("schema", {}).get("$ref", "").rsplit("/", 1)[-1]
        if name in out:
            for key, ex in media.get("examples", {}).items():
                out[name][f"{op['operationId']}__{key}"] = ex["value"]
assert len(out["BodyFitRequest"]) >= 1 and len(out["DrapeRequest"]) >= 3, out  # the contract has examples
json.dump(out, sys.stdout, indent=1)
EOF
"$VENV/python" -c 'import json, sys; d = json.load(open(sys.argv[1])); [print(f"  {k}: {sorted(v)}") for k, v in d.items()]' "$TMP/examples.json"

# ---------------------------------------------------------------------------------------------
say "1. TypeScript: openapi-typescript 7"
mkdir -p "$TMP/ts"
cd "$TMP/ts"
# --default-non-nullable false: openapi-typescript 7 otherwise makes every property with a default
# required, in request bodies too when the schema is a $ref'd component (openapi-ts/openapi-typescript
# #1741, #2489), and the README request (no muscle, no proportions, no start_s...) would not type-check.
npx --yes openapi-typescript@7 "$SPEC" -o "$TMP/ts/api.d.ts" --default-non-nullable false
npx --yes openapi-typescript@7 "$SPEC" -o "$TMP/ts/api_defaults.d.ts" >/dev/null 2>&1

"$VENV/python" - "$TMP/examples.json" >"$TMP/ts/client.ts" <<'EOF'
import json, sys
ex = json.load(open(sys.argv[1]))
print('''import type { components, paths } from "./api";

type DrapeRequest = components["schemas"]["DrapeRequest"];
type BodyFitRequest = components["schemas"]["BodyFitRequest"];
type Problem = components["schemas"]["Problem"];

// type-level checks: Exact<A, B> is true only for the same type (never, unknown and any are not
// equal to string or to an object type)
type Exact<A, B> = (<T>() => T extends A ? 1 : 2) extends <T>() => T extends B ? 1 : 2 ? true : false;
type Assert<T extends true> = T;
type IsAny<T> = 0 extends 1 & T ? true : false;

// the requests: the body of POST /v1/drape (and of POST /v1/jobs) is DrapeRequest, of POST /v1/bodies/fit BodyFitRequest
export type Checks = [
  Assert<Exact<paths["/v1/drape"]["post"]["requestBody"]["content"]["application/json"], DrapeRequest>>,
  Assert<Exact<paths["/v1/jobs"]["post"]["requestBody"]["content"]["application/json"], DrapeRequest>>,
  Assert<Exact<paths["/v1/bodies/fit"]["post"]["requestBody"]["content"]["application/json"], BodyFitRequest>>,
  Assert<Exact<IsAny<DrapeRequest>, false>>,
  Assert<Exact<IsAny<BodyFitRequest>, false>>,
  // the binary answers: both media types, each the schema's `type: string` (openapi-typescript maps
  // `format: binary` to string; at run time the body is read as bytes, below), not never / unknown / any
  Assert<Exact<keyof paths["/v1/drape"]["post"]["responses"][200]["content"], "model/gltf-binary" | "application/x-npz">>,
  Assert<Exact<paths["/v1/drape"]["post"]["responses"][200]["content"]["model/gltf-binary"], string>>,
  Assert<Exact<paths["/v1/drape"]["post"]["responses"][200]["content"]["application/x-npz"], string>>,
  Assert<Exact<keyof paths["/v1/jobs/{job_id}/result"]["get"]["responses"][200]["content"], "model/gltf-binary" | "application/x-npz">>,
  Assert<Exact<paths["/v1/jobs/{job_id}/result"]["get"]["responses"][200]["content"]["model/gltf-binary"], string>>,
  Assert<Exact<paths["/v1/jobs/{job_id}/result"]["get"]["responses"][200]["content"]["application/x-npz"], string>>,
  Assert<Exact<paths["/v1/drape"]["post"]["responses"][422]["content"]["application/problem+json"], Problem>>,
];

type Binary = keyof paths["/v1/drape"]["post"]["responses"][200]["content"];

/** POST /v1/drape: the glb (or npz) as bytes, the problem+json thrown. */
export async function drape(base: string, request: DrapeRequest, accept: Binary = "model/gltf-binary"): Promise<ArrayBuffer> {
  const res = await fetch(`${base}/v1/drape`, {
    method: "POST",
    headers: { "content-type": "application/json", accept },
    body: JSON.stringify(request),
  });
  if (!res.ok) {
    const problem: Problem = await res.json();
    throw new Error(`${problem.status} ${problem.title}: ${problem.detail ?? ""}`);
  }
  return res.arrayBuffer();
}

/** POST /v1/bodies/fit */
export async function fit(base: string, request: BodyFitRequest): Promise<components["schemas"]["BodyFitResponse"]> {
  const res = await fetch(`${base}/v1/bodies/fit`, { method: "POST", headers: { "content-type": "application/json" }, body: JSON.stringify(request) });
  return res.json();
}

// the requests as typed literals (excess-property checked): the README's and the contract's examples''')
for schema, items in ex.items():
    for name, value in items.items():
        print(f"export const {name}_{schema}: {schema} = {json.dumps(value)};")
print('''
// the types do constrain (an unused @ts-expect-error is itself an error)
// @ts-expect-error: a clip name is a string
export const wrongClip: DrapeRequest = { motion: { type: "clip", clip: 42 }, garments: [{ id: "tshirt" }], format: "glb" };
// @ts-expect-error: no such format
export const wrongFormat: DrapeRequest = { motion: { type: "clip", clip: "walk" }, garments: [{ id: "tshirt" }], format: "obj" };
// @ts-expect-error: no such option
export const wrongOption: DrapeRequest = { motion: { type: "clip", clip: "walk" }, garments: [{ id: "tshirt" }], format: "glb", options: { compresion: "meshopt" } };
// @ts-expect-error: the five measurements are required
export const missingMeasurement: BodyFitRequest = { height_cm: 168, chest_cm: 92, waist_cm: 76, hips_cm: 102 };
// @ts-expect-error: gender is female or male
export const wrongGender: BodyFitRequest = { height_cm: 168, chest_cm: 92, waist_cm: 76, hips_cm: 102, inseam_cm: 78, gender: "f" };''')
EOF
TSC=(npx --yes -p typescript@5 tsc --noEmit --strict --target es2022 --lib es2022,dom --module esnext --moduleResolution bundler)
"${TSC[@]}" --version
"${TSC[@]}" client.ts
echo "tsc --noEmit --strict client.ts: OK ($(grep -c '^export const .*_\(Drape\|BodyFit\)Request:' client.ts) requests accepted, $(grep -c '@ts-expect-error' client.ts) wrong ones refused, $(grep -c '^  Assert<' client.ts) type-level checks)"
# for the record: the same file against openapi-typescript's default (--default-non-nullable true)
sed 's#from "./api"#from "./api_defaults"#' client.ts >client_defaults.ts
if "${TSC[@]}" client_defaults.ts >defaults.log 2>&1; then
  echo "(info) with openapi-typescript's defaults the requests type-check too"
else
  echo "(info) with openapi-typescript's defaults (--default-non-nullable true) they do not: $(grep -c 'error TS' defaults.log) errors, e.g."
  grep 'error TS' defaults.log | head -2 | cut -c1-240
fi

# ---------------------------------------------------------------------------------------------
say "2. Python: openapi-python-client"
mkdir -p "$TMP/py"
cd "$TMP/py"
# ruff (a dependency of the generator) formats the output: its post-hooks need it on PATH
PATH=$VENV:$PATH "$VENV/openapi-python-client" generate --path "$SPEC" --config "$PY_CONFIG" --meta none \
  --output-path "$TMP/py/tryon_client" >generate.log 2>&1 || { cat generate.log; exit 1; }
cat generate.log
if grep -qiE 'warning|cannot parse|omitted|unsupported|error' generate.log; then
  echo "FAIL: openapi-python-client warned (above)"; exit 1
fi
# for the record: what the generator drops without the config's content_type_overrides
PATH=$VENV:$PATH "$VENV/openapi-python-client" generate --path "$SPEC" --meta none --output-path "$TMP/py/plain_client" >plain.log 2>&1 || true
echo "(info) without tools/openapi-python-client.yaml: $(grep -c 'response will be omitted' plain.log) responses dropped:"
grep -E '^WARNING parsing' plain.log | sed 's/^/  /' || true

"$VENV/python" - "$TMP/examples.json" <<'EOF'
import importlib, inspect, json, pathlib, sys
import httpx

sys.path.insert(0, ".")
from tryon_client import Client
from tryon_client.models import BodyFitRequest, DrapeRequest
from tryon_client.types import File

examples = json.load(open(sys.argv[1]))

def module_for(method: str, url: str):
    """The generated module of an operation, found by what it sends (not by its generated name)."""
    hits = [p for p in pathlib.Path("tryon_client/api").rglob("*.py") if f'"method": "{method}"' in p.read_text() and f'"url": "{url}"' in p.read_text()]
    assert len(hits) == 1, (method, url, hits)
    return importlib.import_module(".".join(hits[0].with_suffix("").parts))

# the requests through the generated models, unchanged
for schema, model in (("DrapeRequest", DrapeRequest), ("BodyFitRequest", BodyFitRequest)):
    for name, value in examples[schema].items():
        back = model.from_dict(value).to_dict()
        assert back == value, (schema, name, value, back)
        print(f"  {schema}.from_dict({name}).to_dict() == {name}")

GLB = b"glTF\x02\x00\x00\x00" + bytes(range(256)) * 8  # bytes as a server would send them (no network)
sent = []

def server(request: httpx.Request) -> httpx.Response:
    sent.append(request)
    if request.url.path in ("/v1/drape", "/v1/jobs/j1/result"):
        return httpx.Response(200, content=GLB, headers={"content-type": "model/gltf-binary"})
    return httpx.Response(404, json={"type": "about:blank", "title": "Not Found", "status": 404, "detail": "no such path"},
                          headers={"content-type": "application/problem+json"})

client = Client(base_url="http://tryon.test")
client.set_httpx_client(httpx.Client(base_url="http://tryon.test", transport=httpx.MockTransport(server)))

drape = module_for("post", "/v1/drape")
result = module_for("get", "/v1/jobs/{job_id}/result")
for mod in (drape, result):
    ret = str(inspect.signature(mod.sync).return_annotation)
    assert "File" in ret, (mod.__name__, ret)
    print(f"  {mod.__name__}.sync -> {ret}")

readme = examples["DrapeRequest"]["readme"]
got = drape.sync(client=client, body=DrapeRequest.from_dict(readme))
assert isinstance(got, File) and got.payload.read() == GLB, got
assert json.loads(sent[-1].content) == readme and sent[-1].headers["content-type"] == "application/json"
print(f"  drape.sync(README request): File with the {len(GLB)} bytes; the JSON sent == the README request")

got = result.sync(client=client, job_id="j1")
assert isinstance(got, File) and got.payload.read() == GLB, got
print(f"  job result.sync: File with the {len(GLB)} bytes")
print("python client: OK")
EOF
say "OK: both generated clients keep the binary responses and accept the README request"
