// Drives a UnityGaussianSplatting (aras-p, package 1.1.1) renderer with the stream, on the GPU: each
// frame's wire payload (index + f32/f16/q13 bytes, as it arrived) goes once into a GraphicsBuffer and
// the compute kernels in Shaders/OferaSplatUpload.compute decode it and scatter it into the renderer's
// raw splat buffers through the server->GPU permutation. No per-frame managed allocation, no re-pack
// on the main thread (one memcpy of the payload into the mapped buffer, or SetData where locking is
// not available). Compiled only with the scripting define OFERA_GAUSSIAN_SPLATTING (this folder's
// assembly references GaussianSplatting). Needs UnityEngine: not compiled by Tests/run.sh; written
// against Unity 2022.3's API and never run in Unity (see README).
//
// Requirements:
// - UnityGaussianSplatting 1.1.1 with Patches/UnityGaussianSplatting-1.1.1-gpu-buffers.patch (public
//   gpuPosData/gpuOtherData/gpuSHData and the gpuResourcesCreated event);
// - the GaussianSplatAsset made from a PLY of the avatar the server streams (`ofera avatar export`),
//   Quality "Very High" (position Float32, scale Float32, SH Float32, no chunks);
// - a platform with compute shaders (Vulkan on Quest).
// No ghost, no flash: every splat is hidden (NaN position, zero scale; the renderer discards it) as soon
// as the renderer creates its buffers, until the session's neutral state is written; splats no server
// Gaussian maps to stay hidden.
#if OFERA_GAUSSIAN_SPLATTING
using System;
using GaussianSplatting.Runtime;
using Unity.Collections;
using UnityEngine;
using UnityEngine.Rendering;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/Gaussian Splatting Sink (UnityGaussianSplatting)")]
    public sealed class GaussianSplattingSink : GaussianSinkBehaviour, IFrameSink
    {
        [Tooltip("Renderer whose asset was imported from this avatar's PLY with Quality 'Very High' (patched 1.1.1, see Patches/).")]
        public GaussianSplatRenderer splatRenderer;

        [Tooltip("OferaSplatUpload.compute from this package.")]
        public ComputeShader uploadShader;

        [Tooltip("Largest distance (m) between a server Gaussian's neutral position and its splat in the asset.")]
        public float matchTolerance = 1e-5f;

        [Tooltip("Payload buffers in flight (one is written per frame; the GPU may still read the previous ones).")]
        [Range(2, 4)] public int payloadBuffers = 3;

        public enum PayloadUpload { Auto, LockBufferForWrite, SetData }

        [Tooltip("How the payload reaches the GPU. Auto: LockBufferForWrite on Vulkan (Quest), D3D11, D3D12 and Metal, SetData elsewhere (see UsesLockBufferForWrite).")]
        public PayloadUpload payloadUpload = PayloadUpload.Auto;

        const int GroupSize = 256;
        const int PosStride = 12, OtherStride = 16;

        int _kHide, _kF32, _kF16, _kQ13;
        bool _kernelsOk;

        // per session
        int _serverCount, _splats;
        bool _mirrorX, _ready, _haveFirstState;
        GraphicsBuffer _perm, _posTable, _scaleTable;
        readonly FramePayload _neutral = new FramePayload();
        float[] _mirroredSh;

        // per frame
        GraphicsBuffer[] _payload;
        bool[] _lockable;
        int _next;
        uint[] _staging = new uint[0]; // SetData fallback only

        static class Ids
        {
            public static readonly int N = Shader.PropertyToID("_OferaN");
            public static readonly int HasIndex = Shader.PropertyToID("_OferaHasIndex");
            public static readonly int IndexWord = Shader.PropertyToID("_OferaIndexWord");
            public static readonly int PosWord = Shader.PropertyToID("_OferaPosWord");
            public static readonly int RotWord = Shader.PropertyToID("_OferaRotWord");
            public static readonly int ScaleWord = Shader.PropertyToID("_OferaScaleWord");
            public static readonly int ServerCount = Shader.PropertyToID("_OferaServerCount");
            public static readonly int SplatCount = Shader.PropertyToID("_OferaSplatCount");
            public static readonly int MirrorX = Shader.PropertyToID("_OferaMirrorX");
            public static readonly int Payload = Shader.PropertyToID("_OferaPayload");
            public static readonly int ServerToGpu = Shader.PropertyToID("_OferaServerToGpu");
            public static readonly int PosTable = Shader.PropertyToID("_OferaPosTable");
            public static readonly int ScaleTable = Shader.PropertyToID("_OferaScaleTable");
            public static readonly int SplatPos = Shader.PropertyToID("_OferaSplatPos");
            public static readonly int SplatOther = Shader.PropertyToID("_OferaSplatOther");
        }

        /// <summary>This sink takes raw payloads (the GPU decodes): the client need not decode floats for it.</summary>
        public bool NeedsValues { get { return false; } }

        void OnEnable()
        {
            if (splatRenderer == null) splatRenderer = GetComponent<GaussianSplatRenderer>();
            if (splatRenderer == null)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: no GaussianSplatRenderer assigned");
                enabled = false;
                return;
            }
            _kernelsOk = uploadShader != null && SystemInfo.supportsComputeShaders;
            if (_kernelsOk)
            {
                _kHide = uploadShader.FindKernel("CSOferaHide");
                _kF32 = uploadShader.FindKernel("CSOferaDecodeF32");
                _kF16 = uploadShader.FindKernel("CSOferaDecodeF16");
                _kQ13 = uploadShader.FindKernel("CSOferaDecodeQ13");
            }
            else Debug.LogError("[OFERA] GaussianSplattingSink: assign OferaSplatUpload.compute (and use a platform with compute shaders)");
            splatRenderer.gpuResourcesCreated += OnRendererBuffers;
            // the renderer may have created its buffers before this component was enabled: hide now
            // (still before this frame renders)
            if (splatRenderer.gpuPosData != null) OnRendererBuffers(splatRenderer);
        }

        void OnDisable()
        {
            if (splatRenderer != null) splatRenderer.gpuResourcesCreated -= OnRendererBuffers;
            ReleaseSession();
            ReleasePayloadBuffers();
        }

        /// <summary>The renderer (re)created its buffers from the asset: hide everything, then restore the session's state.</summary>
        void OnRendererBuffers(GaussianSplatRenderer r)
        {
            if (!_kernelsOk || r.gpuPosData == null || r.gpuOtherData == null) return;
            int splats = r.asset != null ? r.asset.splatCount : 0;
            DispatchHide(r, splats);
            if (_ready)
            {
                // new buffers hold the raw asset: back to the neutral state (sparse frames carry every moving Gaussian)
                Dispatch(_neutral, r);
                if (_mirroredSh != null && r.gpuSHData != null) r.gpuSHData.SetData(_mirroredSh);
            }
        }

        public override void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state)
        {
            ReleaseSession();
            GaussianSplatAsset asset = splatRenderer != null ? splatRenderer.asset : null;
            if (!_kernelsOk || asset == null || asset.posData == null || asset.otherData == null)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: the renderer has no usable GaussianSplatAsset (or no upload shader)");
                return;
            }
            bool chunked = asset.chunkData != null && asset.chunkData.dataSize > 0;
            if (asset.posFormat != GaussianSplatAsset.VectorFormat.Float32 || asset.scaleFormat != GaussianSplatAsset.VectorFormat.Float32 ||
                asset.shFormat != GaussianSplatAsset.SHFormat.Float32 || chunked)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: the asset must be uncompressed (re-create it with Quality 'Very High': position, scale and SH Float32, no chunks); " +
                               "it has position " + asset.posFormat + ", scale " + asset.scaleFormat + ", SH " + asset.shFormat + (chunked ? ", chunks" : ""));
                return;
            }
            _splats = asset.splatCount;
            NativeArray<float> assetPos = asset.posData.GetData<float>();
            if (assetPos.Length < 3 * _splats || asset.otherData.dataSize < OtherStride * _splats)
            {
                Debug.LogError("[OFERA] GaussianSplattingSink: asset data smaller than " + _splats + " splats of 12 B position + 16 B rotation/scale");
                return;
            }
            // once per session, on the main thread: match server Gaussians to splats (the importer Morton-reorders)
            float[] gpuPos = assetPos.ToArray();
            bool assetMirrored;
            int unmatched;
            int[] serverToGpu = SplatPermutation.Build(avatar.Position, avatar.Count, gpuPos, _splats, matchTolerance, out assetMirrored, out unmatched);
            if (avatar.Count != _splats || unmatched > 0)
                Debug.LogWarning("[OFERA] GaussianSplattingSink: server avatar " + avatar.Count + " Gaussians, asset " + _splats + " splats; " + unmatched +
                                 " server Gaussians found no splat within " + matchTolerance + " m (not shown); splats without a server Gaussian stay hidden");
            _serverCount = avatar.Count;
            // Data arrives in the session's coordinates: with coords=unity (OferaAvatarClient's choice) the server
            // has mirrored it already; with coords=flame the kernel mirrors (_OferaMirrorX).
            _mirrorX = welcome.Coords == "flame";
            // An asset imported from a FLAME-space PLY is the x-mirror of Unity-space data: positions are written
            // in Unity's space anyway; the asset's view-dependent SH is mirrored once so colour matches.
            _mirroredSh = null;
            if (assetMirrored != _mirrorX)
            {
                NativeArray<float> sh = asset.shData.GetData<float>();
                if (sh.Length >= UgsPacking.ShFloat32Stride * _splats)
                {
                    _mirroredSh = sh.ToArray();
                    UgsPacking.MirrorXShFloat32(_mirroredSh, _splats);
                }
            }
            FrameEncoding enc;
            Protocol.TryParseEncoding(welcome.Encoding, out enc);
            uint[] permWords = GpuTables.PermutationWords(serverToGpu);
            _perm = new GraphicsBuffer(GraphicsBuffer.Target.Raw, permWords.Length, 4) { name = "OFERA server->GPU" };
            _perm.SetData(permWords);
            if (enc == FrameEncoding.Q13 && welcome.Quant != null)
            {
                float[] pt = GpuTables.Q13Positions(welcome.Quant);
                _posTable = new GraphicsBuffer(GraphicsBuffer.Target.Raw, pt.Length, 4) { name = "OFERA q13 positions" };
                _posTable.SetData(pt);
                float[] st = GpuTables.Q13Scales(welcome.Quant);
                _scaleTable = new GraphicsBuffer(GraphicsBuffer.Target.Raw, st.Length, 4) { name = "OFERA q13 scales" };
                _scaleTable.SetData(st);
            }
            else
            {
                _posTable = new GraphicsBuffer(GraphicsBuffer.Target.Raw, 1, 4);
                _scaleTable = new GraphicsBuffer(GraphicsBuffer.Target.Raw, 1, 4);
            }
            // payload buffers: the largest frame is a sparse f32 one carrying everything, 11 words a Gaussian
            EnsurePayloadBuffers(11 * Math.Max(1, avatar.Count) + 4);
            GpuTables.NeutralPayload(avatar, _neutral);
            _ready = true;
            _haveFirstState = false;
            GaussianSplatRenderer r = splatRenderer;
            if (r.gpuPosData != null)
            {
                DispatchHide(r, _splats);
                Dispatch(_neutral, r); // the first state: the session's neutral avatar
                if (_mirroredSh != null && r.gpuSHData != null) r.gpuSHData.SetData(_mirroredSh);
                _haveFirstState = true;
            }
        }

        /// <summary>Unused: this sink takes frames (IFrameSink.ApplyFrame); the client skips the CPU state for it.</summary>
        public override void ApplyState(GaussianState state) { }

        public void ApplyFrame(FrameData frame)
        {
            if (!_ready || frame.Payload.Length == 0) return;
            GaussianSplatRenderer r = splatRenderer;
            if (r == null || r.gpuPosData == null) return; // renderer disabled; its re-creation restores the neutral state
            if (!_haveFirstState) { DispatchHide(r, _splats); Dispatch(_neutral, r); _haveFirstState = true; }
            Dispatch(frame.Payload, r);
        }

        public override void Clear()
        {
            // session over: keep the last state on screen until the next session's avatar replaces it
            _ready = false;
        }

        void Dispatch(FramePayload p, GaussianSplatRenderer r)
        {
            if (p.N == 0) return;
            int words = p.Words;
            int slot = _next;
            _next = (_next + 1) % _payload.Length;
            if (_payload[slot] == null || _payload[slot].count < words) EnsurePayloadBuffers(words);
            GraphicsBuffer buf = _payload[slot];
            if (_lockable[slot])
            {
                NativeArray<uint> dst = buf.LockBufferForWrite<uint>(0, words);
                NativeArray<byte>.Copy(p.Bytes, 0, dst.Reinterpret<byte>(4), 0, p.Length);
                buf.UnlockBufferAfterWrite<uint>(words);
            }
            else
            {
                if (_staging.Length < words) _staging = new uint[Math.Max(words, _payload[slot].count)];
                Buffer.BlockCopy(p.Bytes, 0, _staging, 0, p.Length);
                buf.SetData(_staging, 0, 0, words);
            }
            int k = p.Encoding == FrameEncoding.Q13 ? _kQ13 : p.Encoding == FrameEncoding.F16 ? _kF16 : _kF32;
            ComputeShader cs = uploadShader;
            cs.SetInt(Ids.N, p.N);
            cs.SetInt(Ids.HasIndex, p.HasIndex ? 1 : 0);
            cs.SetInt(Ids.IndexWord, p.IndexWord);
            cs.SetInt(Ids.PosWord, p.PositionWord);
            cs.SetInt(Ids.RotWord, p.RotationWord);
            cs.SetInt(Ids.ScaleWord, p.ScaleWord);
            cs.SetInt(Ids.ServerCount, _serverCount);
            cs.SetInt(Ids.SplatCount, _splats);
            cs.SetInt(Ids.MirrorX, _mirrorX ? 1 : 0);
            cs.SetBuffer(k, Ids.Payload, buf);
            cs.SetBuffer(k, Ids.ServerToGpu, _perm);
            cs.SetBuffer(k, Ids.PosTable, _posTable);
            cs.SetBuffer(k, Ids.ScaleTable, _scaleTable);
            cs.SetBuffer(k, Ids.SplatPos, r.gpuPosData);
            cs.SetBuffer(k, Ids.SplatOther, r.gpuOtherData);
            // runs before this frame's rendering, where the renderer computes view data and sorts
            cs.Dispatch(k, (p.N + GroupSize - 1) / GroupSize, 1, 1);
        }

        void DispatchHide(GaussianSplatRenderer r, int splats)
        {
            if (splats <= 0) return;
            ComputeShader cs = uploadShader;
            cs.SetInt(Ids.SplatCount, splats);
            cs.SetBuffer(_kHide, Ids.SplatPos, r.gpuPosData);
            cs.SetBuffer(_kHide, Ids.SplatOther, r.gpuOtherData);
            cs.Dispatch(_kHide, (splats + GroupSize - 1) / GroupSize, 1, 1);
        }

        /// <summary>
        /// Whether payload buffers are created with GraphicsBuffer.UsageFlags.LockBufferForWrite, decided up front
        /// by a capability check rather than by catching an exception: Unity reports an unsupported buffer usage by
        /// logging, not throwing, and has no query for this flag. Documented: LockBufferForWrite returns GPU memory
        /// where the platform can map it, else a temporary CPU buffer that Unity copies (no gain over SetData); the
        /// GPU only reads such a buffer (ByteAddressBuffer, as OferaSplatUpload.compute declares the payload).
        /// Auto uses it where buffers are mapped memory (Vulkan, which the Quest runs; D3D11, D3D12, Metal) and
        /// SetData elsewhere (OpenGL ES / Core: not measured); compute shaders are needed either way.
        /// </summary>
        public static bool UsesLockBufferForWrite(PayloadUpload mode, GraphicsDeviceType api, bool computeShaders)
        {
            if (!computeShaders || mode == PayloadUpload.SetData) return false;
            if (mode == PayloadUpload.LockBufferForWrite) return true;
            switch (api)
            {
                case GraphicsDeviceType.Vulkan:
                case GraphicsDeviceType.Direct3D11:
                case GraphicsDeviceType.Direct3D12:
                case GraphicsDeviceType.Metal:
                    return true;
                default:
                    return false;
            }
        }

        void EnsurePayloadBuffers(int words)
        {
            int n = Mathf.Clamp(payloadBuffers, 2, 4);
            if (_payload != null && _payload.Length == n && _payload[0] != null && _payload[0].count >= words) return;
            ReleasePayloadBuffers();
            _payload = new GraphicsBuffer[n];
            _lockable = new bool[n];
            bool lockable = UsesLockBufferForWrite(payloadUpload, SystemInfo.graphicsDeviceType, SystemInfo.supportsComputeShaders);
            for (int i = 0; i < n; i++)
            {
                // LockBufferForWrite: the payload is copied straight into GPU-visible memory; else SetData from _staging
                _payload[i] = lockable
                    ? new GraphicsBuffer(GraphicsBuffer.Target.Raw, GraphicsBuffer.UsageFlags.LockBufferForWrite, words, 4) { name = "OFERA frame payload" }
                    : new GraphicsBuffer(GraphicsBuffer.Target.Raw, words, 4) { name = "OFERA frame payload" };
                _lockable[i] = lockable;
            }
            _next = 0;
        }

        void ReleasePayloadBuffers()
        {
            if (_payload == null) return;
            foreach (GraphicsBuffer b in _payload) if (b != null) b.Release();
            _payload = null;
        }

        void ReleaseSession()
        {
            _ready = false;
            if (_perm != null) { _perm.Release(); _perm = null; }
            if (_posTable != null) { _posTable.Release(); _posTable = null; }
            if (_scaleTable != null) { _scaleTable.Release(); _scaleTable = null; }
        }
    }
}
#endif
