// Params sessions (PROTOCOL.md 13, OferaAvatarClient's encoding "Params") on the GPU: uploads the session's rig once
// (AvatarData.Rig: its arrays as they arrived, RigGpuWords) and, per frame, the frame's 68 params, then dispatches
// Shaders/OferaRigDeform.compute, which deforms the rig's Gaussians and writes them straight into the same
// UnityGaussianSplatting renderer's raw splat buffers through the server->GPU permutation. Put it next to a
// GaussianSplattingSink on the same renderer (both in the client's Sinks): that sink hides the splats and writes the
// neutral avatar (every Gaussian the rig does not move keeps it); this one moves the rig's Gaussians every frame.
// The receive thread then neither deforms nor decodes (the client's DecodeValues is off when every sink is a GPU
// sink). Compiled only with OFERA_GAUSSIAN_SPLATTING; needs UnityEngine: type-checked by Tests/run.sh, never run in
// Unity (see README). The kernels are run on lavapipe by tests/test_unity_rig_kernel.py.
#if OFERA_GAUSSIAN_SPLATTING
using System;
using GaussianSplatting.Runtime;
using Unity.Collections;
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/Rig Splatting Sink (params sessions, UnityGaussianSplatting)")]
    public sealed class RigSplattingSink : GaussianSinkBehaviour, IFrameSink
    {
        [Tooltip("The renderer the GaussianSplattingSink next to this one drives (asset quality 'Very High', patched 1.1.1).")]
        public GaussianSplatRenderer splatRenderer;

        [Tooltip("OferaRigDeform.compute from this package.")]
        public ComputeShader rigShader;

        [Tooltip("Largest distance (m) between a server Gaussian's neutral position and its splat (as the GaussianSplattingSink's).")]
        public float matchTolerance = 1e-5f;

        const int GroupSize = 256;

        int _kPose, _kVertices, _kFaces, _kGaussians;
        bool _kernelsOk, _ready;
        RigData _rig;
        int _serverCount, _splats;
        GraphicsBuffer _rigWords, _params, _perm, _scratch;

        static class Ids
        {
            public static readonly int Vertices = Shader.PropertyToID("_OferaRigVertices");
            public static readonly int Expr = Shader.PropertyToID("_OferaRigExpr");
            public static readonly int Pose = Shader.PropertyToID("_OferaRigPose");
            public static readonly int FaceCount = Shader.PropertyToID("_OferaRigFaceCount");
            public static readonly int Gaussians = Shader.PropertyToID("_OferaRigGaussians");
            public static readonly int Barycentric = Shader.PropertyToID("_OferaRigBarycentric");
            public static readonly int ServerCount = Shader.PropertyToID("_OferaServerCount");
            public static readonly int SplatCount = Shader.PropertyToID("_OferaSplatCount");
            public static readonly int MirrorX = Shader.PropertyToID("_OferaMirrorX");
            public static readonly int Rig = Shader.PropertyToID("_OferaRig");
            public static readonly int Params = Shader.PropertyToID("_OferaRigParams");
            public static readonly int ServerToGpu = Shader.PropertyToID("_OferaServerToGpu");
            public static readonly int Scratch = Shader.PropertyToID("_OferaRigScratch");
            public static readonly int SplatPos = Shader.PropertyToID("_OferaSplatPos");
            public static readonly int SplatOther = Shader.PropertyToID("_OferaSplatOther");

            /// <summary>The section word offsets, in RigGpuWords order.</summary>
            public static readonly int[] Sections =
            {
                Shader.PropertyToID("_OferaRigIndexWord"), Shader.PropertyToID("_OferaRigJointsWord"),
                Shader.PropertyToID("_OferaRigJointsExprWord"), Shader.PropertyToID("_OferaRigTemplateWord"),
                Shader.PropertyToID("_OferaRigExprBasisWord"), Shader.PropertyToID("_OferaRigPoseRowsWord"),
                Shader.PropertyToID("_OferaRigPoseBasisWord"), Shader.PropertyToID("_OferaRigWeightsWord"),
                Shader.PropertyToID("_OferaRigFaceWord"), Shader.PropertyToID("_OferaRigGaussianFaceWord"),
                Shader.PropertyToID("_OferaRigLocalWord"), Shader.PropertyToID("_OferaRigNormalOffsetWord"),
                Shader.PropertyToID("_OferaRigRotationWord"), Shader.PropertyToID("_OferaRigScaleWord"),
            };
        }

        /// <summary>The kernels deform: the client need not (DecodeValues off when every sink is a GPU sink).</summary>
        public bool NeedsValues { get { return false; } }

        void OnEnable()
        {
            if (splatRenderer == null) splatRenderer = GetComponent<GaussianSplatRenderer>();
            _kernelsOk = rigShader != null && SystemInfo.supportsComputeShaders && splatRenderer != null;
            if (!_kernelsOk)
            {
                Debug.LogError("[OFERA] RigSplattingSink: assign the GaussianSplatRenderer and OferaRigDeform.compute (and use a platform with compute shaders)");
                return;
            }
            _kPose = rigShader.FindKernel("CSOferaRigPose");
            _kVertices = rigShader.FindKernel("CSOferaRigVertices");
            _kFaces = rigShader.FindKernel("CSOferaRigFaces");
            _kGaussians = rigShader.FindKernel("CSOferaRigGaussians");
        }

        void OnDisable() { Release(); }

        public override void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state)
        {
            Release();
            if (avatar.Rig == null) return; // not a params session: the GaussianSplattingSink's frames move the avatar
            if (!_kernelsOk) return;
            GaussianSplatAsset asset = splatRenderer.asset;
            if (asset == null || asset.posData == null || asset.posFormat != GaussianSplatAsset.VectorFormat.Float32)
            {
                Debug.LogError("[OFERA] RigSplattingSink: the renderer needs a GaussianSplatAsset of quality 'Very High' (Float32 positions)");
                return;
            }
            _splats = asset.splatCount;
            NativeArray<float> assetPos = asset.posData.GetData<float>();
            if (assetPos.Length < 3 * _splats) { Debug.LogError("[OFERA] RigSplattingSink: asset positions smaller than its splat count"); return; }
            bool assetMirrored;
            int unmatched;
            // the same match as the GaussianSplattingSink's (the importer Morton-reorders splats), once per session
            int[] serverToGpu = SplatPermutation.Build(avatar.Position, avatar.Count, assetPos.ToArray(), _splats, matchTolerance, out assetMirrored, out unmatched);
            _serverCount = avatar.Count;
            _rig = avatar.Rig;
            uint[] permWords = GpuTables.PermutationWords(serverToGpu);
            _perm = new GraphicsBuffer(GraphicsBuffer.Target.Raw, permWords.Length, 4) { name = "OFERA rig server->GPU" };
            _perm.SetData(permWords);
            uint[] words = _rig.Gpu.Words;
            _rigWords = new GraphicsBuffer(GraphicsBuffer.Target.Raw, words.Length, 4) { name = "OFERA rig" };
            _rigWords.SetData(words);
            _params = new GraphicsBuffer(GraphicsBuffer.Target.Raw, ParamsProtocol.Length, 4) { name = "OFERA rig params" };
            int scratch = _rig.PoseCount + 12 * ParamsProtocol.Joints + 3 * _rig.Vertices + 17 * _rig.Faces;
            _scratch = new GraphicsBuffer(GraphicsBuffer.Target.Raw, Math.Max(1, scratch), 4) { name = "OFERA rig scratch" };
            _ready = true;
        }

        /// <summary>Unused: this sink takes frames (IFrameSink.ApplyFrame).</summary>
        public override void ApplyState(GaussianState state) { }

        public void ApplyFrame(FrameData frame)
        {
            if (!_ready || !frame.HasParams) return;
            GaussianSplatRenderer r = splatRenderer;
            if (r == null || r.gpuPosData == null || r.gpuOtherData == null) return; // renderer disabled or not created yet
            _params.SetData(frame.Params);
            ComputeShader cs = rigShader;
            RigData g = _rig;
            cs.SetInt(Ids.Vertices, g.Vertices);
            cs.SetInt(Ids.Expr, g.ExprDims);
            cs.SetInt(Ids.Pose, g.PoseCount);
            cs.SetInt(Ids.FaceCount, g.Faces);
            cs.SetInt(Ids.Gaussians, g.Gaussians);
            cs.SetInt(Ids.Barycentric, g.Binding == RigBinding.Barycentric ? 1 : 0);
            for (int i = 0; i < RigGpuWords.Sections; i++) cs.SetInt(Ids.Sections[i], g.Gpu.Word[i]);
            cs.SetInt(Ids.ServerCount, _serverCount);
            cs.SetInt(Ids.SplatCount, _splats);
            cs.SetInt(Ids.MirrorX, 1); // the rig deforms in FLAME space; the renderer's buffers are in Unity's
            Bind(_kPose, r);
            cs.Dispatch(_kPose, 1, 1, 1);
            Bind(_kVertices, r);
            cs.Dispatch(_kVertices, Groups(g.Vertices), 1, 1);
            Bind(_kFaces, r);
            cs.Dispatch(_kFaces, Groups(g.Faces), 1, 1);
            Bind(_kGaussians, r);
            cs.Dispatch(_kGaussians, Groups(g.Gaussians), 1, 1); // before this frame's rendering sorts the splats
        }

        static int Groups(int n) { return Math.Max(1, (n + GroupSize - 1) / GroupSize); }

        void Bind(int k, GaussianSplatRenderer r)
        {
            ComputeShader cs = rigShader;
            cs.SetBuffer(k, Ids.Rig, _rigWords);
            cs.SetBuffer(k, Ids.Params, _params);
            cs.SetBuffer(k, Ids.ServerToGpu, _perm);
            cs.SetBuffer(k, Ids.Scratch, _scratch);
            cs.SetBuffer(k, Ids.SplatPos, r.gpuPosData);
            cs.SetBuffer(k, Ids.SplatOther, r.gpuOtherData);
        }

        public override void Clear() { _ready = false; } // session over: the last state stays until the next avatar

        void Release()
        {
            _ready = false;
            _rig = null;
            if (_rigWords != null) { _rigWords.Release(); _rigWords = null; }
            if (_params != null) { _params.Release(); _params = null; }
            if (_perm != null) { _perm.Release(); _perm = null; }
            if (_scratch != null) { _scratch.Release(); _scratch = null; }
        }
    }
}
#endif
