// Drives a UnityGaussianSplatting (aras-p) renderer with the stream: writes positions, rotations and
// scales into its GPU buffers every frame. Compiled only with the scripting define
// OFERA_GAUSSIAN_SPLATTING (this folder's assembly has it as a define constraint and references the
// GaussianSplatting assembly). Needs UnityEngine; not compiled by Tests/run.sh.
//
// Requirements (UnityGaussianSplatting has no official runtime-update API):
// - the GaussianSplatAsset is made from a PLY of the same avatar the server streams, with Quality
//   "Very High" (position and scale Float32, no chunks), so the GPU holds plain floats;
// - the asset's splats are Morton-reordered on import: the sink matches every server Gaussian to the
//   GPU splat at the same neutral position once per session (SplatPermutation, tested in Core) and
//   keeps that server->GPU index permutation;
// - the renderer's private GPU buffers (m_GpuPosData, m_GpuOtherData, m_GpuSHData) are reached by
//   reflection; the asset's data (posData/otherData/shData properties in 1.x, m_* fields before) too.
// Every Gaussian's position, rotation and scale is written in the session's coordinates (Unity's). A PLY
// exported in FLAME space (`ofera avatar export`) imports x-mirrored: the sink detects it while matching
// and then also mirrors the asset's SH once (odd-in-x coefficients), so the head is not a mirror image.
// Opacity and the SH DC colour stay as imported (they never change during a session).
#if OFERA_GAUSSIAN_SPLATTING
using System;
using System.Reflection;
using GaussianSplatting.Runtime;
using Unity.Collections;
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/Gaussian Splatting Sink (UnityGaussianSplatting)")]
    public sealed class GaussianSplattingSink : GaussianSinkBehaviour
    {
        [Tooltip("Renderer whose asset was imported from this avatar's PLY with Quality 'Very High'.")]
        public GaussianSplatRenderer splatRenderer;

        [Tooltip("Largest distance (m) between a server Gaussian's neutral position and its splat in the asset.")]
        public float matchTolerance = 1e-5f;

        const BindingFlags Any = BindingFlags.Public | BindingFlags.NonPublic | BindingFlags.Instance;
        static readonly FieldInfo PosBufferField = typeof(GaussianSplatRenderer).GetField("m_GpuPosData", Any);
        static readonly FieldInfo OtherBufferField = typeof(GaussianSplatRenderer).GetField("m_GpuOtherData", Any);
        static readonly FieldInfo ShBufferField = typeof(GaussianSplatRenderer).GetField("m_GpuSHData", Any);

        int[] _serverToGpu;
        bool _assetMirrored;
        float[] _gpuSh;    // only when the asset is mirrored: its SH with x-odd coefficients negated
        float[] _gpuPos;   // GPU order, 3 floats per splat (plus the asset's padding)
        uint[] _gpuOther;  // GPU order, 4 uints per splat: packed rotation, scale x, y, z (plus padding)
        int _splats;
        GraphicsBuffer _uploadedPos, _uploadedOther, _uploadedSh;
        bool _ready;

        static object Member(object o, params string[] names)
        {
            if (o == null) return null;
            Type t = o.GetType();
            foreach (string n in names)
            {
                PropertyInfo p = t.GetProperty(n, Any);
                if (p != null) return p.GetValue(o, null);
                FieldInfo f = t.GetField(n, Any);
                if (f != null) return f.GetValue(o);
            }
            return null;
        }

        public override void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state)
        {
            _ready = false;
            if (splatRenderer == null) { Debug.LogError("[OFERA] GaussianSplattingSink: assign a GaussianSplatRenderer"); return; }
            if (PosBufferField == null || OtherBufferField == null)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: this UnityGaussianSplatting version has no m_GpuPosData/m_GpuOtherData; the sink needs updating");
                return;
            }
            object asset = Member(splatRenderer, "asset", "m_Asset");
            string posFormat = Convert.ToString(Member(asset, "posFormat", "m_PosFormat"));
            string scaleFormat = Convert.ToString(Member(asset, "scaleFormat", "m_ScaleFormat"));
            TextAsset posData = Member(asset, "posData", "m_PosData") as TextAsset;
            TextAsset otherData = Member(asset, "otherData", "m_OtherData") as TextAsset;
            TextAsset chunkData = Member(asset, "chunkData", "m_ChunkData") as TextAsset;
            TextAsset shData = Member(asset, "shData", "m_SHData") as TextAsset;
            string shFormat = Convert.ToString(Member(asset, "shFormat", "m_SHFormat"));
            object count = Member(asset, "splatCount", "m_SplatCount");
            if (asset == null || posData == null || otherData == null || count == null)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: the renderer has no usable GaussianSplatAsset");
                return;
            }
            if (posFormat != "Float32" || scaleFormat != "Float32" || (chunkData != null && chunkData.dataSize > 0))
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: the asset must be uncompressed (re-create it with Quality 'Very High': " +
                               "position and scale Float32, no chunks); it has position " + posFormat + ", scale " + scaleFormat);
                return;
            }
            _splats = (int)count;
            NativeArray<float> pos = posData.GetData<float>();
            NativeArray<uint> other = otherData.GetData<uint>();
            if (pos.Length < 3 * _splats || other.Length < 4 * _splats)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: asset data smaller than " + _splats + " splats (expected 12 B position and 16 B rotation+scale each)");
                return;
            }
            _gpuPos = pos.ToArray();
            _gpuOther = other.ToArray();
            int unmatched;
            _serverToGpu = SplatPermutation.Build(avatar.Position, avatar.Count, _gpuPos, _splats, matchTolerance, out _assetMirrored, out unmatched);
            _gpuSh = null;
            if (_assetMirrored)
            {
                if (shFormat == "Float32" && shData != null && ShBufferField != null)
                {
                    NativeArray<float> sh = shData.GetData<float>();
                    if (sh.Length >= UgsPacking.ShFloat32Stride * _splats)
                    {
                        _gpuSh = sh.ToArray();
                        UgsPacking.MirrorXShFloat32(_gpuSh, _splats);
                    }
                }
                if (_gpuSh == null)
                    Debug.LogWarning("[OFERA] GaussianSplattingSink: the asset is x-mirrored but its SH could not be mirrored (needs SH format Float32); view-dependent colour will be mirrored");
            }
            if (avatar.Count != _splats || unmatched > 0)
                Debug.LogWarning("[OFERA] GaussianSplattingSink: server avatar has " + avatar.Count + " Gaussians, the asset " + _splats +
                                 "; " + unmatched + " server Gaussians found no splat within " + matchTolerance + " m (they are not animated). " +
                                 "Import the PLY of the avatar the server streams.");
            Debug.Log("[OFERA] GaussianSplattingSink: permutation ready" + (_assetMirrored ? " (asset imported x-mirrored, e.g. from a FLAME-space PLY: converted to Unity's)" : ""));
            _uploadedPos = null;
            _uploadedOther = null;
            _uploadedSh = null;
            _ready = true;
            int gmin, gmax;
            UgsPacking.WriteGpu(state, 0, state.Count - 1, _serverToGpu, false, _gpuPos, _gpuOther, out gmin, out gmax);
            Upload(0, _splats - 1);
        }

        public override void ApplyState(GaussianState state)
        {
            if (!_ready || state.DirtyMax < state.DirtyMin) return;
            int gmin, gmax;
            UgsPacking.WriteGpu(state, state.DirtyMin, state.DirtyMax, _serverToGpu, false, _gpuPos, _gpuOther, out gmin, out gmax);
            if (gmax >= gmin) Upload(gmin, gmax);
        }

        void Upload(int gmin, int gmax)
        {
            GraphicsBuffer posBuf = PosBufferField.GetValue(splatRenderer) as GraphicsBuffer;
            GraphicsBuffer otherBuf = OtherBufferField.GetValue(splatRenderer) as GraphicsBuffer;
            if (posBuf == null || otherBuf == null) return; // renderer disabled or recreating its resources
            if (!ReferenceEquals(posBuf, _uploadedPos) || !ReferenceEquals(otherBuf, _uploadedOther))
            {
                // new buffers (renderer re-enabled, asset reloaded): send everything once
                gmin = 0; gmax = _splats - 1;
                _uploadedPos = posBuf;
                _uploadedOther = otherBuf;
            }
            int n = gmax - gmin + 1;
            posBuf.SetData(_gpuPos, 3 * gmin, 3 * gmin, 3 * n);       // buffers are raw, stride 4
            otherBuf.SetData(_gpuOther, 4 * gmin, 4 * gmin, 4 * n);
            if (_gpuSh != null)
            {
                GraphicsBuffer shBuf = ShBufferField.GetValue(splatRenderer) as GraphicsBuffer;
                if (shBuf != null && !ReferenceEquals(shBuf, _uploadedSh))
                {
                    shBuf.SetData(_gpuSh, 0, 0, UgsPacking.ShFloat32Stride * _splats);
                    _uploadedSh = shBuf;
                }
            }
        }

        public override void Clear() { _ready = false; }
    }
}
#endif
