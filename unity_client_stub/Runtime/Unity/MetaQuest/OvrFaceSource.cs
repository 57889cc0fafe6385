// Quest Pro face tracking through Meta's XR Core SDK (com.meta.xr.sdk.core). Compiled only with the
// scripting define OFERA_META_SDK (this folder's assembly has it as a define constraint and references
// Oculus.VR); the asmdef's version define OFERA_META_SDK_60 is set for com.meta.xr.sdk.core >= 60.0.0.
// Needs UnityEngine and the SDK: not compiled by Tests/run.sh, written against SDK 68 (see README).
//
// What it reads, through the SDK's public API, once per rendered frame after OVRFaceExpressions
// updated (DefaultExecutionOrder below; OVRFaceExpressions has the default order 0):
// - OVRPlugin.GetFaceState2 (v60+; GetFaceState before) with Step.Render and the newest frame: the
//   weights, the validity, the two region confidences (v46+) and the tracker's own sample time
//   FaceState.Time (device seconds);
// - OVRFaceExpressions.TryGetFaceTrackingDataSource (v60+): visual or audio-driven.
// A sample is produced only when the tracker's time changes (the app often renders faster than the
// tracker updates, so the same sample would otherwise be sent again as new) and is stamped with that
// time, converted to OferaClock (see TryGetSample's remarks).
#if OFERA_META_SDK
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/Quest Pro Face Source (OVR)")]
    [DefaultExecutionOrder(100)] // after OVRFaceExpressions (0), before OferaAvatarClient and FaceLogRecorder's reads (200)
    public sealed class OvrFaceSource : FaceSourceBehaviour, IFaceSampleTime
    {
        [Tooltip("OVRFaceExpressions to read (it starts face tracking and asks for the permission); found in the scene when empty.")]
        public OVRFaceExpressions faceExpressions;

        [Tooltip("Send the 70-weight layout (tongue, SDK v60+) when available; else ovr63.")]
        public bool includeTongue;

        OVRPlugin.FaceState _state;
        bool _stateValid;
        int _readFrame = -1;
        double _lastSentTime = double.NaN;
        double _trackerTime;
        long _offsetMicros = long.MaxValue; // OferaClock - tracker clock, smallest seen

        int Length { get { return includeTongue && (int)OVRFaceExpressions.FaceExpression.Max >= 70 ? 70 : 63; } }

        public override string Layout { get { return Length == 70 ? "ovr70" : "ovr63"; } }

        public override bool IsTracking { get { Refresh(); return _stateValid; } }

        void Awake()
        {
            if (faceExpressions == null) faceExpressions = FindAnyObjectByType<OVRFaceExpressions>();
            if (faceExpressions == null)
                Debug.LogWarning("[OFERA] OvrFaceSource: no OVRFaceExpressions in the scene; add one (e.g. on the OVRCameraRig): it starts face tracking.");
        }

        // Reads the face state once per rendered frame, after OVRFaceExpressions (execution order 100 > 0),
        // so this frame's state, not the previous frame's. A caller that runs earlier (order < 100) triggers
        // the read itself: the state comes from the plugin, not from OVRFaceExpressions' copy.
        void Update() { Refresh(); }

        void Refresh()
        {
            if (_readFrame == Time.frameCount) return;
            _readFrame = Time.frameCount;
#if OFERA_META_SDK_60
            bool ok = OVRPlugin.GetFaceState2(OVRPlugin.Step.Render, -1, ref _state);
#else
            bool ok = OVRPlugin.GetFaceState(OVRPlugin.Step.Render, -1, ref _state);
#endif
            _stateValid = ok && _state.Status.IsValid && _state.ExpressionWeights != null && _state.ExpressionWeights.Length >= Length;
            if (_stateValid) _trackerTime = _state.Time;
        }

        /// <summary>
        /// The tracker's sample time, converted to OferaClock microseconds: tracker seconds x 1e6 plus the
        /// smallest (OferaClock now - tracker time) seen so far, i.e. the two clocks aligned at the
        /// quickest observed read. Echoed by the server as `t`, so round trips are measured from the
        /// moment the face was captured (give or take that smallest read delay), not from when it was read.
        /// </summary>
        protected override bool ReadSample(float[] weights, out long timestampMicros)
        {
            timestampMicros = 0;
            Refresh();
            if (!_stateValid) return false;
            double tracker = _state.Time;
            if (tracker == _lastSentTime) return false; // the tracker has not produced a new sample
            long trackerMicros = (long)(tracker * 1e6);
            long offset = OferaClock.NowMicros() - trackerMicros;
            if (offset < _offsetMicros) _offsetMicros = offset;
            int n = Length;
            float[] w = _state.ExpressionWeights;
            for (int i = 0; i < n; i++) weights[i] = w[i];
            _lastSentTime = tracker;
            timestampMicros = trackerMicros + _offsetMicros;
            return true;
        }

        /// <summary>IFaceSampleTime (FaceLogRecorder's Face_Time): the newest valid sample's tracker time, in seconds.</summary>
        public bool TryGetSampleTime(out double seconds)
        {
            Refresh();
            seconds = _trackerTime;
            return _stateValid && _trackerTime > 0;
        }

        /// <summary>Region confidences (lower, upper; SDK v46+) and data source (audio-driven; SDK v60+, else false).</summary>
        public override bool TryGetConfidence(out float lower, out float upper, out bool audioDriven)
        {
            lower = 1f; upper = 1f; audioDriven = false;
            Refresh();
            if (!_stateValid || _state.ExpressionWeightConfidences == null || _state.ExpressionWeightConfidences.Length < 2) return false;
            lower = _state.ExpressionWeightConfidences[(int)OVRFaceExpressions.FaceRegionConfidence.Lower];
            upper = _state.ExpressionWeightConfidences[(int)OVRFaceExpressions.FaceRegionConfidence.Upper];
#if OFERA_META_SDK_60
            OVRFaceExpressions.FaceTrackingDataSource source;
            if (faceExpressions != null && faceExpressions.TryGetFaceTrackingDataSource(out source))
                audioDriven = source == OVRFaceExpressions.FaceTrackingDataSource.Audio;
#endif
            return true;
        }
    }
}
#endif
