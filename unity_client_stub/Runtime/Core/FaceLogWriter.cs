// Face-log CSV writer, version 1 (protocol/FACELOG.md): what `ofera.sources.read_facelog` reads.
// UnityEngine-free, C# 7.2.
using System;
using System.Globalization;
using System.IO;
using System.Text;

namespace Ofera.Client
{
    /// <summary>
    /// Writes "# ofera facelog 1", "# layout: ...", optional metadata comments, the header
    /// (time, optional Face_Time, the layout's names, optional confidence_lower/confidence_upper, optional
    /// data_source) and one row per sample: time %.6f seconds, values %.6g, '\n' line ends.
    /// With <see cref="TrackerTime"/> the file has a Face_Time column (the tracker's own sample time, device
    /// seconds, %.6f), which `read_facelog` reads as a Quest log: one sample per new Face_Time.
    /// </summary>
    public sealed class FaceLogWriter : IDisposable
    {
        readonly TextWriter _w;
        readonly string[] _names;
        readonly bool _confidence;
        readonly bool _dataSource;
        readonly StringBuilder _line = new StringBuilder(1024);
        bool _headerDone;
        bool _trackerTime;
        double _lastTime = double.NegativeInfinity;

        public string Layout { get; private set; }
        public int Length { get { return _names.Length; } }
        public long Rows { get; private set; }

        /// <summary>
        /// Write a Face_Time column (set before the first row; the header is written with it). Rows then
        /// need a tracker time: <see cref="Write(double, double, float[], float, float, string)"/>.
        /// </summary>
        public bool TrackerTime
        {
            get { return _trackerTime; }
            set
            {
                if (_headerDone) throw new InvalidOperationException("TrackerTime must be set before the first row");
                _trackerTime = value;
            }
        }

        /// <param name="metadata">extra "# key: value" lines (pairs key, value), e.g. "headset", "Quest Pro".</param>
        public FaceLogWriter(TextWriter writer, string layout, string source, bool withConfidence = false,
                             bool withDataSource = false, params string[] metadata)
        {
            _names = Layouts.Names(layout);
            if (_names == null) throw new ArgumentException("unknown layout '" + layout + "'; expected one of " + string.Join(", ", Protocol.Layouts));
            if (metadata != null && metadata.Length % 2 != 0) throw new ArgumentException("metadata must be key, value pairs");
            _w = writer;
            _w.NewLine = "\n";
            Layout = layout;
            _confidence = withConfidence;
            _dataSource = withDataSource;
            _w.Write("# ofera facelog 1\n# layout: " + layout + "\n");
            if (!string.IsNullOrEmpty(source)) _w.Write("# source: " + OneLine(source) + "\n");
            if (metadata != null)
                for (int i = 0; i < metadata.Length; i += 2)
                {
                    string key = metadata[i].Trim();
                    if (key.Length == 0 || key.Equals("layout", StringComparison.OrdinalIgnoreCase) || string.IsNullOrEmpty(metadata[i + 1])) continue;
                    _w.Write("# " + key + ": " + OneLine(metadata[i + 1]) + "\n");
                }
        }

        /// <summary>Opens a UTF-8 file (no BOM) for writing.</summary>
        public static FaceLogWriter Create(string path, string layout, string source, bool withConfidence = false,
                                           bool withDataSource = false, params string[] metadata)
        {
            StreamWriter sw = new StreamWriter(path, false, new UTF8Encoding(false), 1 << 16);
            return new FaceLogWriter(sw, layout, source, withConfidence, withDataSource, metadata);
        }

        static string OneLine(string s)
        {
            return string.Join(" ", s.Split((char[])null, StringSplitOptions.RemoveEmptyEntries));
        }

        void Header()
        {
            _line.Length = 0;
            _line.Append("time");
            if (_trackerTime) _line.Append(",Face_Time");
            for (int i = 0; i < _names.Length; i++) _line.Append(',').Append(_names[i]);
            if (_confidence) _line.Append(",confidence_lower,confidence_upper");
            if (_dataSource) _line.Append(",data_source");
            _line.Append('\n');
            _w.Write(_line.ToString());
            _headerDone = true;
        }

        /// <summary>
        /// One sample. <paramref name="timeSeconds"/> must not decrease; weights must be finite (the
        /// reader rejects nan/inf). dataSource: "visual" or "audio" (used only with withDataSource).
        /// </summary>
        public void Write(double timeSeconds, float[] weights, float confidenceLower = 1f, float confidenceUpper = 1f,
                          string dataSource = "visual")
        {
            if (_trackerTime) throw new InvalidOperationException("this log has a Face_Time column: pass the tracker time");
            Row(timeSeconds, double.NaN, weights, confidenceLower, confidenceUpper, dataSource);
        }

        /// <summary>
        /// One sample with the tracker's own time (<see cref="TrackerTime"/> on): <paramref name="trackerSeconds"/>
        /// is the device-clock time of the face state (Meta: OVRPlugin.FaceState.Time), finite.
        /// </summary>
        public void Write(double timeSeconds, double trackerSeconds, float[] weights, float confidenceLower = 1f,
                          float confidenceUpper = 1f, string dataSource = "visual")
        {
            if (!_trackerTime) throw new InvalidOperationException("set TrackerTime before the first row to write Face_Time");
            if (double.IsNaN(trackerSeconds) || double.IsInfinity(trackerSeconds)) throw new ArgumentException("tracker time must be finite");
            Row(timeSeconds, trackerSeconds, weights, confidenceLower, confidenceUpper, dataSource);
        }

        void Row(double timeSeconds, double trackerSeconds, float[] weights, float confidenceLower, float confidenceUpper,
                 string dataSource)
        {
            if (weights == null || weights.Length < _names.Length)
                throw new ArgumentException("layout " + Layout + " needs " + _names.Length + " weights");
            if (double.IsNaN(timeSeconds) || double.IsInfinity(timeSeconds)) throw new ArgumentException("time must be finite");
            if (timeSeconds < _lastTime) throw new ArgumentException("time must not decrease (" + timeSeconds + " after " + _lastTime + ")");
            if (!_headerDone) Header();
            _lastTime = timeSeconds;
            _line.Length = 0;
            _line.Append(timeSeconds.ToString("F6", CultureInfo.InvariantCulture));
            if (_trackerTime) _line.Append(',').Append(trackerSeconds.ToString("F6", CultureInfo.InvariantCulture));
            for (int i = 0; i < _names.Length; i++)
            {
                float v = weights[i];
                if (float.IsNaN(v) || float.IsInfinity(v)) v = 0f; // a face log holds finite numbers only
                _line.Append(',').Append(FormatG6(v));
            }
            if (_confidence) _line.Append(',').Append(FormatG6(confidenceLower)).Append(',').Append(FormatG6(confidenceUpper));
            if (_dataSource) _line.Append(',').Append(dataSource == "audio" ? "audio" : "visual");
            _line.Append('\n');
            _w.Write(_line.ToString());
            Rows++;
        }

        /// <summary>Python's "%.6g" of the float's double value (e.g. 0.0123, 1e-05, 0.333333).</summary>
        public static string FormatG6(double v)
        {
            if (v == 0) return (1 / v < 0) ? "-0" : "0";
            string s = v.ToString("G6", CultureInfo.InvariantCulture);
            int e = s.IndexOf('E');
            if (e < 0) return s;
            // .NET: 1E-05 / 1.5E+20 ; Python: 1e-05 / 1.5e+20 (exponent at least two digits)
            string mant = s.Substring(0, e);
            string exp = s.Substring(e + 1);
            char sign = exp[0] == '-' ? '-' : '+';
            string digits = exp.TrimStart('+', '-').TrimStart('0');
            if (digits.Length < 2) digits = digits.PadLeft(2, '0');
            return mant + "e" + sign + digits;
        }

        public void Flush() { _w.Flush(); }

        public void Dispose()
        {
            if (!_headerDone) Header();
            _w.Flush();
            _w.Dispose();
        }
    }
}
