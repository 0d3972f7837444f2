"""EXT_meshopt_compression of a glb's buffer views (meshoptimizer's codecs, from PyPI).

Each eligible buffer view's bytes are replaced by the meshopt encoding of its elements and the
view moves into a "fallback" buffer that holds no data (the extension is required, so players
must decode: three.js with ``GLTFLoader.setMeshoptDecoder``, model-viewer, Babylon.js):
- vertex data (``ATTRIBUTES`` mode): positions, normals, UVs, skin joints and weights, morph
  targets, animation keyframes: any view whose element size (its ``byteStride``, else its
  accessors' element size) is a multiple of 4 bytes up to 256 and divides its length;
- triangle indices (``TRIANGLES`` mode).
No filters: the data is already quantized (KHR_mesh_quantization). A view whose encoding is not
smaller, or that cannot be encoded (1-byte scalar morph weights of odd length), stays as is.
Encoder format version 0, which every decoder reads. gzip on top still pays (the codec leaves
byte-level redundancy for a general-purpose compressor, as it is designed to).
"""
from __future__ import annotations

import numpy as np

EXTENSION = "EXT_meshopt_compression"
_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_ELEMENT_ARRAY_BUFFER = 34963


def available() -> bool:
    """Whether the meshoptimizer package (the optional ``compress`` extra) is installed."""
    try:
        import meshoptimizer  # noqa: F401
    except ImportError:
        return False
    return True


def compress(gltf: dict, blob: bytes) -> tuple[dict, bytes]:
    """Meshopt-encode the buffer views of a one-buffer glTF: returns the new JSON (``gltf`` is
    not modified) and the new binary buffer."""
    import meshoptimizer

    gltf = {**gltf, "bufferViews": [dict(v) for v in gltf["bufferViews"]]}
    element: dict[int, int] = {}
    for acc in gltf["accessors"]:
        element.setdefault(acc["bufferView"], _COMPONENT_BYTES[acc["componentType"]] * _COMPONENTS[acc["type"]])
    index_views = {gltf["accessors"][p["indices"]]["bufferView"] for m in gltf["meshes"] for p in m["primitives"]
                   if "indices" in p and p.get("mode", 4) == 4}
    parts: list[bytes] = []
    length = 0
    compressed = 0
    for i, view in enumerate(gltf["bufferViews"]):
        raw = blob[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
        encoded = None
        if i in index_views:
            stride = element[i]
            indices = np.frombuffer(raw, np.uint16 if stride == 2 else np.uint32)
            if len(indices) % 3 == 0 and len(indices):
                encoded = meshoptimizer.encode_index_buffer(indices, len(indices), int(indices.max()) + 1)
                ext = {"mode": "TRIANGLES", "byteStride": stride, "count": len(indices)}
        else:
            stride = view.get("byteStride", element.get(i))
            if stride and stride % 4 == 0 and stride <= 256 and len(raw) % stride == 0 and raw:
                count = len(raw) // stride
                encoded = meshoptimizer.encode_vertex_buffer(np.frombuffer(raw, np.uint8), count, stride)
                ext = {"mode": "ATTRIBUTES", "byteStride": stride, "count": count}
        data = bytes(encoded) if encoded is not None and len(encoded) < len(raw) else raw
        if data is not raw:
            # the view keeps its (virtual) place in the fallback buffer; its bytes live in buffer 0
            view["buffer"] = 1
            view["extensions"] = {EXTENSION: {"buffer": 0, "byteOffset": length, "byteLength": len(data), **ext}}
            compressed += 1
        else:
            view["byteOffset"] = length
        parts.append(data)
        pad = -len(data) % 4
        parts.append(b"\0" * pad)
        length += len(data) + pad
    if not compressed:
        return gltf, blob
    gltf["buffers"] = [{"byteLength": length},
                       {"byteLength": len(blob), "extensions": {EXTENSION: {"fallback": True}}}]
    gltf["extensionsUsed"] = sorted(set(gltf.get("extensionsUsed", [])) | {EXTENSION})
    gltf["extensionsRequired"] = sorted(set(gltf.get("extensionsRequired", [])) | {EXTENSION})
    return gltf, b"".join(parts)
