// The MonoBehaviour that ties it together: connects to the server (OferaClient, Core), feeds it the
// face source's samples, applies the avatar and frames to the sinks on the main thread, and shows
// statistics in the inspector. Needs UnityEngine; not compiled by Tests/run.sh.
using System.Collections.Generic;
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/OFERA Avatar Client")]
    public sealed class OferaAvatarClient : MonoBehaviour
    {
        public enum FrameEncodingChoice { F32, F16, Q13 }

        [Header("Server")]
        [Tooltip("ws://host:port/v1/stream (the address `ofera serve` prints); wss:// behind TLS.")]
        public string serverUrl = "ws://192.168.1.20:8000/v1/stream";
        [Tooltip("Avatar id on the server; 'default' is the server's default avatar.")]
        public string avatarId = "default";
        [Tooltip("Frame encoding: F32 exact (40 B/Gaussian), F16 (20 B), Q13 quantised (13 B).")]
        public FrameEncodingChoice encoding = FrameEncodingChoice.Q13;
        [Tooltip("Ask for sparse frames (only the Gaussians expressions move).")]
        public bool sparse = true;
        [Tooltip("Headset profile for the server's blendshape alignment (e.g. quest_pro); empty to omit.")]
        public string deviceProfile = "quest_pro";
        [Tooltip("Access token, if the server requires one.")]
        public string token = "";
        public bool reconnect = true;

        [Header("Face and avatar")]
        [Tooltip("Where the blendshapes come from (OvrFaceSource on a Quest Pro, SyntheticFaceSource for tests). Empty: the avatar stays neutral.")]
        public FaceSourceBehaviour faceSource;
        [Tooltip("Where the Gaussians go. Empty: a PointCloudSink is added to this GameObject.")]
        public GaussianSinkBehaviour[] sinks;
        [Tooltip("Log connection events to the console.")]
        public bool logEvents = true;

        [Header("Statistics (read only)")]
        public string status = "stopped";
        public int gaussians;
        public long framesReceived;
        public long framesDroppedBeforeApply;
        public long framesSkippedByServer;
        public float roundTripMsP50;
        public float roundTripMsP95;
        public float serverMsP50;

        OferaClient _client;
        GaussianState _state;
        int _session = -1;
        float[] _weights = new float[70];
        readonly List<IGaussianSink> _sinks = new List<IGaussianSink>();
        float _nextStats;

        public OferaClient Client { get { return _client; } }

        void OnEnable()
        {
            _sinks.Clear();
            if (sinks != null) foreach (GaussianSinkBehaviour s in sinks) if (s != null) _sinks.Add(s);
            if (_sinks.Count == 0)
            {
                PointCloudSink points = GetComponent<PointCloudSink>(); // not '??': Unity objects compare to null with ==
                if (points == null) points = gameObject.AddComponent<PointCloudSink>();
                _sinks.Add(points);
            }

            OferaClientOptions o = new OferaClientOptions();
            o.Url = serverUrl;
            o.Avatar = string.IsNullOrEmpty(avatarId) ? "default" : avatarId;
            o.Layout = faceSource != null ? faceSource.Layout : "ovr63";
            o.Encoding = encoding == FrameEncodingChoice.F32 ? "f32" : encoding == FrameEncodingChoice.F16 ? "f16" : "q13";
            o.Coords = "unity";
            o.Sparse = sparse;
            o.Device = deviceProfile;
            o.Token = token;
            o.Reconnect = reconnect;
            try
            {
                _client = new OferaClient(o);
            }
            catch (System.ArgumentException e)
            {
                Debug.LogError("[OFERA] " + e.Message);
                enabled = false;
                return;
            }
            _client.Start();
        }

        void OnDisable()
        {
            if (_client != null) _client.Stop(500);
            _client = null;
            _state = null;
            _session = -1;
            foreach (IGaussianSink s in _sinks) s.Clear();
        }

        void Update()
        {
            if (_client == null) return;
            ClientEvent e;
            while (_client.TryDequeueEvent(out e))
            {
                status = _client.Status.ToString();
                if (!logEvents) continue;
                if (e.Kind == ClientEventKind.ServerError && e.Error != null && !e.Error.Fatal) Debug.LogWarning("[OFERA] " + e.Message);
                else if (e.Kind == ClientEventKind.ProtocolError || e.Kind == ClientEventKind.ServerError) Debug.LogError("[OFERA] " + e.Message);
                else Debug.Log("[OFERA] " + e.Message);
            }

            AvatarData avatar; Welcome welcome; int session;
            if (_client.TryTakeAvatar(out avatar, out welcome, out session))
            {
                _state = new GaussianState(avatar);
                _session = session;
                gaussians = avatar.Count;
                foreach (IGaussianSink s in _sinks) s.SetAvatar(avatar, welcome, _state);
                _state.ClearDirty();
            }

            long t;
            if (faceSource != null && faceSource.TryGetSample(_weights, out t))
                _client.SubmitBlendshapes(_weights, t);

            FrameData f = _client.TryTakeFrame();
            if (f != null && _state != null && f.SessionNumber == _session && _state.Apply(f))
            {
                foreach (IGaussianSink s in _sinks) s.ApplyState(_state);
                _state.ClearDirty();
            }

            if (Time.unscaledTime >= _nextStats)
            {
                _nextStats = Time.unscaledTime + 0.5f;
                ClientStats st = _client.Stats;
                status = _client.Status.ToString();
                framesReceived = st.FramesReceived;
                framesDroppedBeforeApply = st.FramesDropped;
                framesSkippedByServer = st.FramesSkippedByServer;
                roundTripMsP50 = st.RoundTrip.Percentile(50) * 1e-3f;
                roundTripMsP95 = st.RoundTrip.Percentile(95) * 1e-3f;
                serverMsP50 = st.ServerTotal.Percentile(50) * 1e-3f;
            }
        }
    }
}
