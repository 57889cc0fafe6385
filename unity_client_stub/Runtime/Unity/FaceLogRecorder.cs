// Records a face source to a face-log CSV (protocol/FACELOG.md) that `ofera replay` and
// `ofera.sources.read_facelog` read. Needs UnityEngine; the writer itself (FaceLogWriter) is in Core
// and tested under mono.
using System;
using System.IO;
using UnityEngine;

namespace Ofera.Client.Unity
{
    [AddComponentMenu("OFERA/Face Log Recorder")]
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

        public bool recordOnEnable;

        public bool IsRecording { get { return _writer != null; } }
        public string CurrentPath { get; private set; }

        FaceLogWriter _writer;
        float[] _weights = new float[70];
        bool _withConfidence;
        long _t0 = -1;

        void OnEnable() { if (recordOnEnable) StartRecording(); }
        void OnDisable() { StopRecording(); }

        public void StartRecording()
        {
            if (_writer != null || faceSource == null) return;
            string name = string.Format(fileName, DateTime.Now.ToString("yyyyMMdd_HHmmss"));
            CurrentPath = Path.Combine(Application.persistentDataPath, name);
            float lo, up; bool audio;
            _withConfidence = recordConfidence && faceSource.TryGetConfidence(out lo, out up, out audio);
            _writer = FaceLogWriter.Create(CurrentPath, faceSource.Layout, sourceDescription, _withConfidence, _withConfidence,
                                           "headset", headset, "unity", Application.unityVersion);
            _t0 = -1;
            Debug.Log("[OFERA] recording face log to " + CurrentPath);
        }

        public void StopRecording()
        {
            if (_writer == null) return;
            _writer.Dispose();
            Debug.Log("[OFERA] face log written: " + CurrentPath + " (" + _writer.Rows + " rows)");
            _writer = null;
        }

        void Update()
        {
            if (_writer == null || faceSource == null) return;
            long t;
            if (!faceSource.TryGetSample(_weights, out t)) return;
            if (_t0 < 0) _t0 = t;
            float lo = 1f, up = 1f; bool audio = false;
            if (_withConfidence) faceSource.TryGetConfidence(out lo, out up, out audio);
            _writer.Write((t - _t0) * 1e-6, _weights, lo, up, audio ? "audio" : "visual");
        }
    }
}
