// Latency statistics over a sliding window (thread-safe, allocation-free after construction).
using System;
using System.Diagnostics;

namespace Ofera.Client
{
    /// <summary>Monotonic client clock in microseconds (the `t` the client sends and the server echoes).</summary>
    public static class OferaClock
    {
        static readonly Stopwatch Watch = Stopwatch.StartNew();
        static readonly double TicksToMicros = 1e6 / Stopwatch.Frequency;

        public static long NowMicros() { return (long)(Watch.ElapsedTicks * TicksToMicros); }
    }

    /// <summary>Count/mean/min/max over every sample and percentiles over the last <c>window</c> samples (µs).</summary>
    public sealed class LatencyStats
    {
        readonly object _lock = new object();
        readonly long[] _ring;
        readonly long[] _sorted;
        int _next, _filled;
        long _count, _min = long.MaxValue, _max = long.MinValue;
        double _sum;

        public LatencyStats(int window = 4096)
        {
            _ring = new long[Math.Max(1, window)];
            _sorted = new long[_ring.Length];
        }

        public void Add(long micros)
        {
            lock (_lock)
            {
                _ring[_next] = micros;
                _next = (_next + 1) % _ring.Length;
                if (_filled < _ring.Length) _filled++;
                _count++;
                _sum += micros;
                if (micros < _min) _min = micros;
                if (micros > _max) _max = micros;
            }
        }

        public void Reset()
        {
            lock (_lock) { _next = 0; _filled = 0; _count = 0; _sum = 0; _min = long.MaxValue; _max = long.MinValue; }
        }

        public long Count { get { lock (_lock) return _count; } }
        public double Mean { get { lock (_lock) return _count == 0 ? 0 : _sum / _count; } }
        public long Min { get { lock (_lock) return _count == 0 ? 0 : _min; } }
        public long Max { get { lock (_lock) return _count == 0 ? 0 : _max; } }

        /// <summary>Percentile p (0..100) of the window, nearest rank; 0 when empty.</summary>
        public long Percentile(double p)
        {
            lock (_lock)
            {
                if (_filled == 0) return 0;
                Array.Copy(_ring, _sorted, _filled);
                Array.Sort(_sorted, 0, _filled);
                int rank = (int)Math.Ceiling(p / 100.0 * _filled) - 1;
                if (rank < 0) rank = 0;
                if (rank >= _filled) rank = _filled - 1;
                return _sorted[rank];
            }
        }

        public string Summary(string unit = "ms")
        {
            double f = unit == "ms" ? 1e-3 : 1.0;
            return string.Format(System.Globalization.CultureInfo.InvariantCulture,
                "n={0} mean={1:F2} p50={2:F2} p95={3:F2} p99={4:F2} max={5:F2} {6}",
                Count, Mean * f, Percentile(50) * f, Percentile(95) * f, Percentile(99) * f, Max * f, unit);
        }
    }
}
