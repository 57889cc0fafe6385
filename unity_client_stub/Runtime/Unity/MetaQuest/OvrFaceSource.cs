// Quest Pro face tracking through Meta's OVRFaceExpressions (Meta XR Core SDK).
// Compiled only with the scripting define OFERA_META_SDK (this folder's assembly has it as a define
// constraint and references Oculus.VR). Needs UnityEngine; not compiled by Tests/run.sh.
#if OFERA_META_SDK
using UnityEngine;

namespace Ofera.Client.Unity
{
    /// <summary>
    /// Reads the 63 (XR_FB_face_tracking) or 70 (XR_FB_face_tracking2, with the tongue) weights of
    /// OVRFaceExpressions once per frame. OVRFaceExpressions.FaceExpression uses the OpenXR order, which
    /// is the protocol's ovr63/ovr70 order.
    /// Set-up: an OVRFaceExpressions component in the scene (OVRCameraRig), face tracking enabled in the
    /// OVRManager (Quest features: Face Tracking Support) and the face-tracking permission granted.
    /// </summary>
    [AddComponentMenu("OFERA/Quest Pro Face Source (OVR)")]
    public sealed class OvrFaceSource : FaceSourceBehaviour
    {
        [Tooltip("OVRFaceExpressions to read; found in the scene when empty.")]
        public OVRFaceExpressions faceExpressions;

        [Tooltip("Send the 70-weight layout (tongue) when the SDK provides it; else ovr63.")]
        public bool includeTongue;

        int Length { get { return includeTongue && (int)OVRFaceExpressions.FaceExpression.Max >= 70 ? 70 : 63; } }

        public override string Layout { get { return Length == 70 ? "ovr70" : "ovr63"; } }

        public override bool IsTracking { get { return faceExpressions != null && faceExpressions.ValidExpressions; } }

        void Awake()
        {
            if (faceExpressions == null) faceExpressions = FindObjectOfType<OVRFaceExpressions>();
            if (faceExpressions == null)
                Debug.LogWarning("[OFERA] OvrFaceSource: no OVRFaceExpressions in the scene; add one (e.g. on the OVRCameraRig).");
        }

        protected override bool ReadSample(float[] weights, out long timestampMicros)
        {
            timestampMicros = OferaClock.NowMicros();
            if (faceExpressions == null || !faceExpressions.ValidExpressions) return false;
            int n = Length;
            for (int i = 0; i < n; i++)
            {
                float w;
                if (!faceExpressions.TryGetFaceExpressionWeight((OVRFaceExpressions.FaceExpression)i, out w)) return false;
                weights[i] = w;
            }
            return true; // OVRFaceExpressions refreshes once per rendered frame: one sample per frame
        }

        public override bool TryGetConfidence(out float lower, out float upper, out bool audioDriven)
        {
            audioDriven = false;
            lower = 1f; upper = 1f;
            if (faceExpressions == null) return false;
            bool a = faceExpressions.TryGetWeightConfidence(OVRFaceExpressions.FaceRegionConfidence.Lower, out lower);
            bool b = faceExpressions.TryGetWeightConfidence(OVRFaceExpressions.FaceRegionConfidence.Upper, out upper);
            return a && b;
        }
    }
}
#endif
