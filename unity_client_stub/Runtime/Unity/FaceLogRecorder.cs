// Records a face source to a face-log CSV (protocol/FACELOG.md) that `ofera replay` and
// `ofera.sources.read_facelog` read. Needs UnityEngine; the writer itself (FaceLogWriter) is in Core
// and tested under mono.
using System;
using System.IO;
using UnityEngine;

namespace Ofera.Client.Unity
{
    /// <summary>
    /// A face source that knows when the tracker took its newest sample, on the tracker's own clock
    /// (Meta: OVRPlugin.FaceState.Time, device seconds). The recorder writes it as Face_Time, so that a
    /// replay sends each tracker sample once, at its own time, however often the app's frames repeat it.
    /// </summary>
    public interface IFaceSampleTime
    {
        /// <summary>The newest sample's tracker time in seconds; false if unknown.</summary>
        bool TryGetSampleTime(out double seconds);
    }

    [AddComponentMenu("OFERA/Face Log Recorder")]
    [DefaultExecutionOrder(200)] // reads after the face source (OvrFaceSource: 100), itself after OVRFaceExpressions (0)
    public sealed class FaceLogRecorder : MonoBehaviour
    {
        [Tooltip("Face source to record (e.g. OvrFaceSource).")]
        public FaceSourceBehaviour faceSource;

        [Tooltip("File name under Application.persistentDataPath; {0} is replaced by the date and time.")]
        public string fileName = "facelog_{0}.csv";

        [Tooltip("Free text for the '# source:' line.")]
        public string sourceDescription = "Quest Pro, OFERA Unity recorder";

        [Tooltip("Headset name for the '# headset:' line.")]
        public string headset = "Quest Pro";

        [Tooltip("Write confidence_lower/confidence_upper/data_source columns when the source provides them.")]
        public bool recordConfidence = true;

        [Tooltip("Write the tracker's own sample time (Face_Time) when the source provides it (IFaceSampleTime, e.g. OvrFaceSource).")]
        public bool recordTrackerTime = true;

        public bool recordOnEnable;

        /// <summary>True from StartRecording to StopRecording (the file itself opens at the first valid sample).</summary>
        public bool IsRecording { get; private set; }
        public string CurrentPath { get; private set; }

        FaceLogWriter _writer;
        readonly float[] _weights = new float[70];
        bool _withConfidence;
        IFaceSampleTime _trackerClock;
        double _lastTrackerTime = double.NaN;
        long _t0 = -1;

        void OnEnable() { if (recordOnEnable) StartRecording(); }
        void OnDisable() { StopRecording(); }

        /// <summary>
        /// Starts a recording. The file is created at the first valid sample (tracking on), when the
        /// columns are decided: confidences if the source gives them then, Face_Time if a tracker clock
        /// answers then. Nothing is written while tracking has not started.
        /// </summary>
        public void StartRecording()
        {
            if (IsRecording || faceSource == null) return;
            string name = string.Format(fileName, DateTime.Now.ToString("yyyyMMdd_HHmmss"));
            CurrentPath = Path.Combine(Application.persistentDataPath, name);
            IsRecording = true;
            _writer = null;
            _t0 = -1;
            _lastTrackerTime = double.NaN;
            Debug.Log("[OFERA] recording face log to " + CurrentPath + " from the first valid sample");
        }

        public void StopRecording()
        {
            if (!IsRecording) return;
            IsRecording = false;
            if (_writer == null)
            {
                Debug.Log("[OFERA] face log not written: tracking never delivered a valid sample");
                return;
            }
            _writer.Dispose();
            Debug.Log("[OFERA] face log written: " + CurrentPath + " (" + _writer.Rows + " rows)");
            _writer = null;
        }

        void Open()
        {
            float lo, up; bool audio;
            _withConfidence = recordConfidence && faceSource.TryGetConfidence(out lo, out up, out audio);
            _trackerClock = null;
            if (recordTrackerTime)
            {
                IFaceSampleTime clock = faceSource as IFaceSampleTime;
                double probe;
                if (clock != null && clock.TryGetSampleTime(out probe)) _trackerClock = clock;
            }
            _writer = FaceLogWriter.Create(CurrentPath, faceSource.Layout, sourceDescription, _withConfidence, _withConfidence,
                                           "headset", headset, "unity", Application.unityVersion);
            _writer.TrackerTime = _trackerClock != null;
        }

        void Update()
        {
            if (!IsRecording || faceSource == null) return;
            long t;
            if (!faceSource.IsTracking || !faceSource.TryGetSample(_weights, out t)) return;
            if (_writer == null) Open();
            if (_t0 < 0) _t0 = t;
            float lo = 1f, up = 1f; bool audio = false;
            if (_withConfidence) faceSource.TryGetConfidence(out lo, out up, out audio);
            string source = audio ? "audio" : "visual";
            if (_trackerClock == null)
            {
                _writer.Write((t - _t0) * 1e-6, _weights, lo, up, source);
                return;
            }
            double tracker;
            if (!_trackerClock.TryGetSampleTime(out tracker) || tracker == _lastTrackerTime) return; // no new tracker sample
            _lastTrackerTime = tracker;
            _writer.Write((t - _t0) * 1e-6, tracker, _weights, lo, up, source);
        }
    }
}
