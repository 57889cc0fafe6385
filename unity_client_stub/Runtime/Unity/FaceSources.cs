// Face sources: the generic interface, a MonoBehaviour base the inspector can reference, and a
// synthetic source for projects without a headset. Needs UnityEngine (not compiled by Tests/run.sh).
using UnityEngine;

namespace Ofera.Client.Unity
{
    /// <summary>Anything that produces blendshape weights in one of the protocol's layouts.</summary>
    public interface IFaceSource
    {
        /// <summary>Protocol layout of the weights: ovr63, ovr70, arkit52, arkit51, mediapipe52 or livelink61.</summary>
        string Layout { get; }

        /// <summary>True while the source delivers real data (tracking on, permission granted).</summary>
        bool IsTracking { get; }

        /// <summary>
        /// Copies the newest sample into <paramref name="weights"/> (at least the layout's length) and
        /// its capture time on <see cref="OferaClock"/> (µs). Returns false when there is no new sample
        /// since the previous call; called once per rendered frame from the main thread.
        /// </summary>
        bool TryGetSample(float[] weights, out long timestampMicros);

        /// <summary>Optional per-sample extras for recordings (Meta v2): confidences and data source; false if unknown.</summary>
        bool TryGetConfidence(out float lower, out float upper, out bool audioDriven);
    }

    /// <summary>
    /// Base class so a face source can be assigned in the inspector. Reads the device at most once per
    /// rendered frame (<see cref="ReadSample"/>) and gives that sample to every caller of that frame (the
    /// avatar client and a recorder can share one source).
    /// </summary>
    public abstract class FaceSourceBehaviour : MonoBehaviour, IFaceSource
    {
        public abstract string Layout { get; }
        public abstract bool IsTracking { get; }

        /// <summary>Reads the device; false if there is no new sample.</summary>
        protected abstract bool ReadSample(float[] weights, out long timestampMicros);

        readonly float[] _cache = new float[70];
        int _cacheFrame = -1;
        bool _cacheValid;
        long _cacheT;

        public bool TryGetSample(float[] weights, out long timestampMicros)
        {
            if (Time.frameCount != _cacheFrame)
            {
                _cacheFrame = Time.frameCount;
                _cacheValid = ReadSample(_cache, out _cacheT);
            }
            timestampMicros = _cacheT;
            if (!_cacheValid) return false;
            System.Array.Copy(_cache, weights, Mathf.Min(weights.Length, _cache.Length));
            return true;
        }

        public virtual bool TryGetConfidence(out float lower, out float upper, out bool audioDriven)
        {
            lower = 1f; upper = 1f; audioDriven = false;
            return false;
        }
    }

    /// <summary>
    /// Animated weights for testing without a headset (jaw, smile and blinks in the ovr63 layout, or
    /// the matching ARKit shapes in arkit52), one sample per frame at up to <see cref="rateHz"/>.
    /// </summary>
    [AddComponentMenu("OFERA/Synthetic Face Source")]
    public sealed class SyntheticFaceSource : FaceSourceBehaviour
    {
        public enum SyntheticLayout { Ovr63, Arkit52 }

        public SyntheticLayout layout = SyntheticLayout.Ovr63;
        [Range(1f, 120f)] public float rateHz = 72f;
        [Range(0f, 1f)] public float amplitude = 0.8f;

        float _next;

        public override string Layout { get { return layout == SyntheticLayout.Ovr63 ? "ovr63" : "arkit52"; } }
        public override bool IsTracking { get { return isActiveAndEnabled; } }

        protected override bool ReadSample(float[] weights, out long timestampMicros)
        {
            timestampMicros = OferaClock.NowMicros();
            float now = Time.realtimeSinceStartup;
            if (now < _next) return false;
            _next = now + 1f / Mathf.Max(1f, rateHz);
            System.Array.Clear(weights, 0, weights.Length);
            float jaw = amplitude * (0.5f + 0.5f * Mathf.Sin(now * 2.1f));
            float smile = amplitude * (0.5f + 0.5f * Mathf.Sin(now * 0.9f + 1f));
            float blink = Mathf.Repeat(now, 4f) < 0.15f ? 1f : 0f;
            if (layout == SyntheticLayout.Ovr63)
            {
                weights[24] = jaw;                      // JAW_DROP
                weights[32] = smile; weights[33] = smile; // LIP_CORNER_PULLER_L/R
                weights[12] = blink; weights[13] = blink; // EYES_CLOSED_L/R
            }
            else
            {
                weights[17] = jaw;                      // jawOpen
                weights[23] = smile; weights[24] = smile; // mouthSmileLeft/Right
                weights[0] = blink; weights[7] = blink;   // eyeBlinkLeft/Right
            }
            return true;
        }
    }
}
