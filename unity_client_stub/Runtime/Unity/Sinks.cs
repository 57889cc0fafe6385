// Avatar sinks: where decoded Gaussians go. The point-cloud sink needs nothing but UnityEngine, so a
// bare project can see the stream. Needs UnityEngine; not compiled by Tests/run.sh.
using UnityEngine;
using UnityEngine.Rendering;

namespace Ofera.Client.Unity
{
    /// <summary>Receives the avatar once per session and the updated Gaussian state after each frame (main thread).</summary>
    public interface IGaussianSink
    {
        /// <summary>A new session's static avatar (session coordinates; Unity's with coords = unity).</summary>
        void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state);

        /// <summary>
        /// The state after one or more frames; Gaussians [state.DirtyMin, state.DirtyMax] (server order)
        /// may have changed. Do not clear the dirty range: the caller does after every sink ran.
        /// </summary>
        void ApplyState(GaussianState state);

        /// <summary>The session ended; keep showing the last state or hide, as suits the sink.</summary>
        void Clear();
    }

    /// <summary>
    /// A sink that takes each decoded frame itself (with its wire payload, FrameData.Payload) instead of
    /// the CPU-side state: the GPU upload path. When every sink of an avatar is an IFrameSink with
    /// NeedsValues false, the client neither decodes floats nor keeps a GaussianState for it.
    /// </summary>
    public interface IFrameSink
    {
        bool NeedsValues { get; }
        /// <summary>Main thread, once per frame taken; the frame is valid until the next take.</summary>
        void ApplyFrame(FrameData frame);
    }

    /// <summary>Base class so sinks can be assigned in the inspector.</summary>
    public abstract class GaussianSinkBehaviour : MonoBehaviour, IGaussianSink
    {
        public abstract void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state);
        public abstract void ApplyState(GaussianState state);
        public virtual void Clear() { }
    }

    /// <summary>
    /// Shows every Gaussian as a point (Mesh, MeshTopology.Points) coloured by its SH DC term and
    /// opacity. A debugging view, not a splat renderer: no sizes, no view-dependent colour.
    /// Uses the "Ofera/Points" shader of this package unless a material is given.
    /// </summary>
    [AddComponentMenu("OFERA/Point Cloud Sink")]
    [RequireComponent(typeof(MeshFilter), typeof(MeshRenderer))]
    public sealed class PointCloudSink : GaussianSinkBehaviour
    {
        [Tooltip("Material for the points; default: a new material with the Ofera/Points shader.")]
        public Material material;
        [Tooltip("Points with opacity below this are not drawn.")]
        [Range(0f, 1f)] public float minOpacity = 0.05f;
        [Tooltip("Point size in pixels (honoured on Vulkan/OpenGL ES/Metal, always 1 on Direct3D 11).")]
        [Range(1f, 10f)] public float pointSize = 2f;

        Mesh _mesh;
        Vector3[] _vertices;
        int _count;

        void Awake()
        {
            _mesh = new Mesh();
            _mesh.name = "OFERA Gaussians (points)";
            _mesh.indexFormat = IndexFormat.UInt32;
            _mesh.MarkDynamic();
            GetComponent<MeshFilter>().sharedMesh = _mesh;
            MeshRenderer mr = GetComponent<MeshRenderer>();
            if (material == null)
            {
                Shader shader = Shader.Find("Ofera/Points");
                if (shader == null)
                {
                    Debug.LogWarning("[OFERA] shader Ofera/Points not found (add it to Always Included Shaders, or assign a material); using Sprites/Default");
                    shader = Shader.Find("Sprites/Default");
                }
                material = new Material(shader);
            }
            material.SetFloat("_PointSize", pointSize);
            mr.sharedMaterial = material;
            mr.shadowCastingMode = ShadowCastingMode.Off;
            mr.receiveShadows = false;
        }

        public override void SetAvatar(AvatarData avatar, Welcome welcome, GaussianState state)
        {
            if (_mesh == null) Awake();
            _count = avatar.Count;
            _vertices = new Vector3[_count];
            Color32[] colors = new Color32[_count];
            int k3 = avatar.K * 3;
            const float C0 = 0.28209479f;
            int kept = 0;
            for (int i = 0; i < _count; i++)
            {
                float r = 0.5f + C0 * avatar.Sh[i * k3];
                float g = 0.5f + C0 * avatar.Sh[i * k3 + 1];
                float b = 0.5f + C0 * avatar.Sh[i * k3 + 2];
                float a = avatar.Opacity[i];
                colors[i] = new Color32((byte)(Mathf.Clamp01(r) * 255f), (byte)(Mathf.Clamp01(g) * 255f), (byte)(Mathf.Clamp01(b) * 255f), (byte)(Mathf.Clamp01(a) * 255f));
                if (a >= minOpacity) kept++;
            }
            int[] indices = new int[kept];
            for (int i = 0, j = 0; i < _count; i++) if (avatar.Opacity[i] >= minOpacity) indices[j++] = i;
            CopyPositions(state, 0, _count - 1);
            _mesh.Clear();
            _mesh.SetVertices(_vertices);
            _mesh.SetColors(colors);
            _mesh.SetIndices(indices, MeshTopology.Points, 0, false);
            _mesh.RecalculateBounds();
            Bounds bounds = _mesh.bounds;
            bounds.Expand(0.1f); // room for expressions, so the avatar is not culled
            _mesh.bounds = bounds;
        }

        void CopyPositions(GaussianState s, int from, int to)
        {
            float[] p = s.Position;
            for (int i = from; i <= to; i++) _vertices[i] = new Vector3(p[3 * i], p[3 * i + 1], p[3 * i + 2]);
        }

        public override void ApplyState(GaussianState state)
        {
            if (_vertices == null || state.Count != _count || state.DirtyMax < state.DirtyMin) return;
            CopyPositions(state, state.DirtyMin, state.DirtyMax);
            Bounds b = _mesh.bounds;
            _mesh.SetVertices(_vertices);  // keeps the index buffer; re-uploads the positions
            _mesh.bounds = b;
        }

        public override void Clear() { }

        void OnDestroy()
        {
            if (_mesh != null) Destroy(_mesh);
        }
    }
}
