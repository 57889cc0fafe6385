// The MonoBehaviour that ties it together: connects to the server (OferaClient, Core), feeds it the
// face source's samples, applies the avatar and frames to the sinks on the main thread, and shows
// statistics in the inspector. In a room (PROTOCOL.md 12) it spawns one instance of memberPrefab per
// publishing member that joins (oneself too with Receive Self), each with its own sinks (and so its own
// server->GPU permutation), removes it when the member leaves, and places it at the member's head pose when
// a MemberPoseSource knows it; watch-only members are only counted. Needs UnityEngine; type-checked by
// Tests/run.sh against Tests/UnityStandIn.cs.
using System.Collections.Generic;
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/OFERA Avatar Client")]
    [DefaultExecutionOrder(200)] // after the face source (OvrFaceSource: 100) and OVRFaceExpressions / GaussianSplatRenderer (0)
    public sealed class OferaAvatarClient : MonoBehaviour
    {
        public enum FrameEncodingChoice { F32, F16, Q13, Params }

        [Header("Server")]
        [Tooltip("ws://host:port/v1/stream (the address `ofera serve` prints); wss:// behind TLS.")]
        public string serverUrl = "ws://192.168.1.20:8000/v1/stream";
        [Tooltip("Avatar id on the server; 'default' is the server's default avatar.")]
        public string avatarId = "default";
        [Tooltip("Frame encoding: F32 exact (40 B/Gaussian), F16 (20 B), Q13 quantised (13 B); Params: 68 values a frame (about 300 B) and this client deforms the avatar from the rig sent at the handshake (add a RigSplattingSink next to the GaussianSplattingSink; CPU sinks get the C# deformation).")]
        public FrameEncodingChoice encoding = FrameEncodingChoice.Q13;
        [Tooltip("Ask for sparse frames (only the Gaussians expressions move).")]
        public bool sparse = true;
        [Tooltip("Headset profile for the server's blendshape alignment (e.g. quest_pro); empty to omit.")]
        public string deviceProfile = "quest_pro";
        [Tooltip("Access token, if the server requires one.")]
        public string token = "";
        [Tooltip("Most Gaussians to render per avatar (hello.max_gaussians; the server streams a reduced avatar). 0: no limit.")]
        public int maxGaussians;
        public bool reconnect = true;

        [Header("Face and avatar")]
        [Tooltip("Where the blendshapes come from (OvrFaceSource on a Quest Pro, SyntheticFaceSource for tests). Empty: the avatar stays neutral.")]
        public FaceSourceBehaviour faceSource;
        [Tooltip("Where the Gaussians go. Empty: a PointCloudSink is added to this GameObject.")]
        public GaussianSinkBehaviour[] sinks;
        [Tooltip("Log connection events to the console.")]
        public bool logEvents = true;

        [Header("Room (several avatars)")]
        [Tooltip("Room to join; empty: a plain v1 session (one avatar). A server without rooms ignores it.")]
        public string room = "";
        [Tooltip("Send this headset's face (publish); off: watch only.")]
        public bool publishFace = true;
        [Tooltip("Also receive one's own avatar in the room.")]
        public bool receiveSelf;
        [Tooltip("Room token, if the server has a room secret (hex HMAC-SHA256 of the room name, from your app server).")]
        public string roomToken = "";
        [Tooltip("Instantiated once per member who joins; its GaussianSinkBehaviours (e.g. GaussianSplatRenderer + GaussianSplattingSink, or a PointCloudSink) show that member.")]
        public GameObject memberPrefab;
        [Tooltip("Parent of the spawned members (default: this object).")]
        public Transform memberParent;
        [Tooltip("Head poses of members (the protocol carries none: they come from your networking layer). Empty: members stay where spawned.")]
        public MemberPoseSource poseSource;
        [Tooltip("Where a member's avatar sits relative to its head pose (FLAME's origin is near the head's centre).")]
        public Vector3 headOffset = Vector3.zero;
        [Tooltip("Spacing of members spawned without a pose (along this object's x axis).")]
        public float spawnSpacing = 0.6f;

        [Header("Statistics (read only)")]
        public string status = "stopped";
        public int gaussians;
        public long framesReceived;
        public long framesDroppedBeforeApply;
        public long framesSkippedByServer;
        public float roundTripMsP50;
        public float roundTripMsP95;
        public float serverMsP50;
        public int members;
        [Tooltip("Watch-only members who joined (they have no avatar).")]
        public int watchers;

        /// <summary>One shown avatar: its sinks, and the CPU state only if a sink needs it.</summary>
        sealed class View
        {
            public readonly List<IGaussianSink> Sinks = new List<IGaussianSink>();
            public readonly List<IFrameSink> FrameSinks = new List<IFrameSink>();
            public bool NeedsState;
            public GaussianState State;
            public int Session = -1;
            public GameObject Instance; // members only

            public void Collect(IEnumerable<GaussianSinkBehaviour> sinks)
            {
                foreach (GaussianSinkBehaviour s in sinks)
                {
                    if (s == null) continue;
                    Sinks.Add(s);
                    IFrameSink fs = s as IFrameSink;
                    if (fs != null) FrameSinks.Add(fs);
                    if (fs == null || fs.NeedsValues) NeedsState = true;
                }
            }

            public void SetAvatar(AvatarData avatar, Welcome welcome, int session)
            {
                Session = session;
                State = NeedsState ? new GaussianState(avatar) : null;
                foreach (IGaussianSink s in Sinks) s.SetAvatar(avatar, welcome, State);
                if (State != null) State.ClearDirty();
            }

            public void Apply(FrameData f)
            {
                if (f == null || f.SessionNumber != Session) return;
                foreach (IFrameSink fs in FrameSinks) fs.ApplyFrame(f);
                if (State != null && f.HasValues && State.Apply(f))
                {
                    foreach (IGaussianSink s in Sinks) if (!(s is IFrameSink) || ((IFrameSink)s).NeedsValues) s.ApplyState(State);
                    State.ClearDirty();
                }
            }
        }

        OferaClient _client;
        readonly View _own = new View();
        readonly Dictionary<string, View> _members = new Dictionary<string, View>();
        readonly List<string> _memberIds = new List<string>();
        readonly Dictionary<string, int> _watching = new Dictionary<string, int>(); // watch-only member -> its session
        float[] _weights = new float[70];
        float _nextStats;

        public OferaClient Client { get { return _client; } }

        void OnEnable()
        {
            _own.Sinks.Clear(); _own.FrameSinks.Clear(); _own.NeedsState = false;
            if (sinks != null) _own.Collect(sinks);
            if (_own.Sinks.Count == 0 && string.IsNullOrEmpty(room))
            {
                PointCloudSink points = GetComponent<PointCloudSink>(); // not '??': Unity objects compare to null with ==
                if (points == null) points = gameObject.AddComponent<PointCloudSink>();
                _own.Collect(new GaussianSinkBehaviour[] { points });
            }
            // what the sinks need decides what the receive thread does: GPU sinks take the wire payload,
            // CPU sinks the decoded floats
            bool wantPayload = _own.FrameSinks.Count > 0, wantValues = _own.NeedsState;
            if (memberPrefab != null)
            {
                View probe = new View();
                probe.Collect(memberPrefab.GetComponentsInChildren<GaussianSinkBehaviour>(true));
                wantPayload |= probe.FrameSinks.Count > 0;
                wantValues |= probe.NeedsState;
            }

            OferaClientOptions o = new OferaClientOptions();
            o.Url = serverUrl;
            o.Avatar = string.IsNullOrEmpty(avatarId) ? "default" : avatarId;
            o.Layout = faceSource != null ? faceSource.Layout : "ovr63";
            o.Encoding = encoding == FrameEncodingChoice.F32 ? "f32" : encoding == FrameEncodingChoice.F16 ? "f16"
                : encoding == FrameEncodingChoice.Params ? ParamsProtocol.Encoding : "q13";
            o.Coords = "unity";
            o.Sparse = sparse;
            o.Device = deviceProfile;
            o.Token = token;
            o.Reconnect = reconnect;
            if (maxGaussians > 0) o.MaxGaussians = maxGaussians;
            o.KeepPayload = wantPayload;
            o.DecodeValues = wantValues || !wantPayload;
            if (!string.IsNullOrEmpty(room))
            {
                o.Room = room;
                o.Publish = publishFace;
                o.Self = receiveSelf;
                o.RoomToken = roomToken;
            }
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
            _own.State = null;
            _own.Session = -1;
            foreach (IGaussianSink s in _own.Sinks) s.Clear();
            RemoveMembers(int.MaxValue);
        }

        void RemoveMembers(int olderThanSession)
        {
            _memberIds.Clear();
            foreach (KeyValuePair<string, View> kv in _members) if (kv.Value.Session < olderThanSession) _memberIds.Add(kv.Key);
            foreach (KeyValuePair<string, int> kv in _watching) if (kv.Value < olderThanSession) _memberIds.Add(kv.Key);
            foreach (string id in _memberIds) RemoveMember(id);
        }

        void RemoveMember(string id)
        {
            if (_watching.Remove(id)) watchers = _watching.Count;
            View v;
            if (!_members.TryGetValue(id, out v)) return;
            foreach (IGaussianSink s in v.Sinks) s.Clear();
            if (v.Instance != null) Destroy(v.Instance);
            _members.Remove(id);
            members = _members.Count;
        }

        void SpawnMember(RoomEvent e)
        {
            RemoveMember(e.Member); // a re-join brings a new avatar
            if (memberPrefab == null)
            {
                Debug.LogWarning("[OFERA] member " + e.Member + " joined but no Member Prefab is set: not shown");
                return;
            }
            Transform parent = memberParent != null ? memberParent : transform;
            GameObject go = Instantiate(memberPrefab, parent);
            go.name = "OFERA member " + e.Member;
            go.transform.localPosition = new Vector3(spawnSpacing * (_members.Count + 1), 0f, 0f);
            go.transform.localRotation = Quaternion.identity;
            View v = new View();
            v.Instance = go;
            v.Collect(go.GetComponentsInChildren<GaussianSinkBehaviour>(true));
            v.SetAvatar(e.Avatar, e.Welcome, e.Session); // each member's sinks build their own permutation
            _members[e.Member] = v;
            members = _members.Count;
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
                gaussians = avatar.Count;
                _own.SetAvatar(avatar, welcome, session);
                RemoveMembers(session); // members of an older session are gone
            }

            RoomEvent re;
            while (_client.TryTakeRoomEvent(out re))
            {
                if (logEvents) Debug.Log("[OFERA] room: " + re);
                if (re.Session != _client.SessionNumber) continue; // stale
                RemoveMembers(re.Session);
                if (re.Kind == RoomEventKind.Left) RemoveMember(re.Member);
                else if (re.Avatar != null) SpawnMember(re);
                else { _watching[re.Member] = re.Session; watchers = _watching.Count; } // watch-only: nothing to show
            }

            long t;
            if (faceSource != null && faceSource.TryGetSample(_weights, out t) && (string.IsNullOrEmpty(room) || publishFace))
                _client.SubmitBlendshapes(_weights, t);

            _own.Apply(_client.TryTakeFrame());
            foreach (KeyValuePair<string, View> kv in _members) kv.Value.Apply(_client.TryTakeFrame(kv.Key));

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

        void LateUpdate()
        {
            if (poseSource == null) return;
            foreach (KeyValuePair<string, View> kv in _members)
            {
                Vector3 p; Quaternion q;
                if (kv.Value.Instance == null || !poseSource.TryGetHeadPose(kv.Key, out p, out q)) continue;
                kv.Value.Instance.transform.SetPositionAndRotation(p + q * headOffset, q);
            }
        }
    }
}
