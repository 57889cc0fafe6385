// Test program for the Unity-independent core (compiled and run by Tests/run.sh under mono).
// Usage: mono TestMain.exe --vectors DIR [--live ws://host:port/v1/stream] [--python python3] [--frames 100]
// Prints one line per check and ends with exactly "N passed, N failed". C# 7.2.
using System;
using System.Collections.Generic;
using System.Diagnostics;
using System.Globalization;
using System.IO;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;
using Ofera.Client;

namespace Ofera.Client.Tests
{
    // ---------------------------------------------------------------- a tiny JSON reader
    static class Json
    {
        public static object Parse(string s)
        {
            int i = 0;
            object v = Value(s, ref i);
            Ws(s, ref i);
            if (i != s.Length) throw new FormatException("trailing characters at " + i);
            return v;
        }

        static void Ws(string s, ref int i) { while (i < s.Length && char.IsWhiteSpace(s[i])) i++; }

        static object Value(string s, ref int i)
        {
            Ws(s, ref i);
            char c = s[i];
            if (c == '{')
            {
                Dictionary<string, object> d = new Dictionary<string, object>();
                List<string> order = new List<string>();
                i++; Ws(s, ref i);
                if (s[i] == '}') { i++; return d; }
                while (true)
                {
                    Ws(s, ref i);
                    string k = Str(s, ref i);
                    Ws(s, ref i);
                    if (s[i] != ':') throw new FormatException("expected ':' at " + i);
                    i++;
                    d[k] = Value(s, ref i);
                    order.Add(k);
                    Ws(s, ref i);
                    if (s[i] == ',') { i++; continue; }
                    if (s[i] == '}') { i++; break; }
                    throw new FormatException("expected ',' or '}' at " + i);
                }
                d["\u0000order"] = order;
                return d;
            }
            if (c == '[')
            {
                List<object> l = new List<object>();
                i++; Ws(s, ref i);
                if (s[i] == ']') { i++; return l; }
                while (true)
                {
                    l.Add(Value(s, ref i));
                    Ws(s, ref i);
                    if (s[i] == ',') { i++; continue; }
                    if (s[i] == ']') { i++; break; }
                    throw new FormatException("expected ',' or ']' at " + i);
                }
                return l;
            }
            if (c == '"') return Str(s, ref i);
            if (s.Substring(i).StartsWith("true")) { i += 4; return true; }
            if (s.Substring(i).StartsWith("false")) { i += 5; return false; }
            if (s.Substring(i).StartsWith("null")) { i += 4; return null; }
            int st = i;
            while (i < s.Length && "+-0123456789.eE".IndexOf(s[i]) >= 0) i++;
            string num = s.Substring(st, i - st);
            if (num.Length == 0) throw new FormatException("unexpected character '" + c + "' at " + i);
            long l64;
            if (num.IndexOfAny(new[] { '.', 'e', 'E' }) < 0 && long.TryParse(num, NumberStyles.AllowLeadingSign, CultureInfo.InvariantCulture, out l64)) return l64;
            return double.Parse(num, NumberStyles.Float, CultureInfo.InvariantCulture);
        }

        static string Str(string s, ref int i)
        {
            if (s[i] != '"') throw new FormatException("expected string at " + i);
            i++;
            StringBuilder b = new StringBuilder();
            while (s[i] != '"')
            {
                char c = s[i++];
                if (c != '\\') { b.Append(c); continue; }
                char e = s[i++];
                switch (e)
                {
                    case 'n': b.Append('\n'); break;
                    case 't': b.Append('\t'); break;
                    case 'r': b.Append('\r'); break;
                    case 'b': b.Append('\b'); break;
                    case 'f': b.Append('\f'); break;
                    case 'u': b.Append((char)Convert.ToInt32(s.Substring(i, 4), 16)); i += 4; break;
                    default: b.Append(e); break;
                }
            }
            i++;
            return b.ToString();
        }
    }

    static class J
    {
        public static Dictionary<string, object> O(object o) { return (Dictionary<string, object>)o; }
        public static List<object> L(object o) { return (List<object>)o; }
        public static bool Has(Dictionary<string, object> d, string k) { return d.ContainsKey(k) && d[k] != null; }
        public static long I(object o) { return o is long ? (long)o : (long)(double)o; }
        public static double D(object o) { return o is long ? (long)o : (double)o; }

        public static void Flatten(object o, List<double> into)
        {
            List<object> l = o as List<object>;
            if (l != null) { foreach (object x in l) Flatten(x, into); return; }
            into.Add(D(o));
        }

        public static double[] Flat(object o)
        {
            List<double> r = new List<double>();
            Flatten(o, r);
            return r.ToArray();
        }

        /// <summary>A `{dtype, shape, values}` field's values, flattened.</summary>
        public static double[] Values(Dictionary<string, object> field) { return Flat(field["values"]); }
    }

    static class Program
    {
        static int _passed, _failed;
        static readonly List<string> Failures = new List<string>();

        static void Check(bool ok, string name, string detail = null)
        {
            if (ok) { _passed++; Console.WriteLine("PASS " + name); }
            else
            {
                _failed++;
                string line = "FAIL " + name + (detail != null ? ": " + detail : "");
                Failures.Add(line);
                Console.WriteLine(line);
            }
        }

        static void Run(string name, Action body)
        {
            try { body(); }
            catch (Exception e) { Check(false, name, e.GetType().Name + ": " + e.Message + "\n" + e.StackTrace); }
        }

        static byte[] Hex(string h)
        {
            byte[] b = new byte[h.Length / 2];
            for (int i = 0; i < b.Length; i++) b[i] = Convert.ToByte(h.Substring(2 * i, 2), 16);
            return b;
        }

        static string ToHex(byte[] b, int off, int len)
        {
            StringBuilder s = new StringBuilder(len * 2);
            for (int i = 0; i < len; i++) s.Append(b[off + i].ToString("x2"));
            return s.ToString();
        }

        /// <summary>Max |a - b| relative to max(1e-30, |b|)... returns the worst mismatch description or null.</summary>
        static string Compare(float[] got, int offset, double[] want, double absTol, double relTol)
        {
            for (int i = 0; i < want.Length; i++)
            {
                double g = got[offset + i], w = want[i];
                double tol = absTol + relTol * Math.Abs(w);
                if (!(Math.Abs(g - w) <= tol))
                    return "element " + i + ": got " + g.ToString("R", CultureInfo.InvariantCulture) + ", want " + w.ToString("R", CultureInfo.InvariantCulture);
            }
            return null;
        }

        static int Main(string[] args)
        {
            string vectors = null, live = null, python = null;
            bool benchRig = false;
            int frames = 100;
            for (int i = 0; i < args.Length; i++)
            {
                if (args[i] == "--vectors") vectors = args[++i];
                else if (args[i] == "--live") live = args[++i];
                else if (args[i] == "--python") python = args[++i];
                else if (args[i] == "--frames") frames = int.Parse(args[++i]);
                else if (args[i] == "--bench-rig") benchRig = true;
            }
            if (benchRig) return RigTests.Bench(live, 200); // one JSON line: the C# params deformation time
            Console.WriteLine("OFERA Unity client core tests (mono " + Environment.Version + ")");
            if (vectors != null) Run("tables", delegate { TableTests(vectors); });
            if (vectors != null) VectorTests(vectors);
            UnitTests(python);
            if (vectors != null) SessionTests(vectors);
            RoomTests.Unit(Run, Check); // RoomTests.cs (PROTOCOL.md 12)
            if (vectors != null) PayloadTests(vectors);
            if (vectors != null) Run("rig frames", delegate { RigTests.Frames(vectors, Check); }); // PROTOCOL.md 13
            if (vectors != null) Run("params sessions", delegate { RigTests.Sessions(vectors, Check); });
            if (vectors != null) Run("params rooms", delegate { RigTests.RoomSessions(vectors, Check); });
            if (live != null) LiveTests(live, frames);
            if (live != null) RoomTests.Live(live, python, Run, Check, WaitFor); // RoomTests.cs (PROTOCOL.md 12)
            if (live != null && vectors != null) // params against the server (PROTOCOL.md 13), the real capture if present
                Run("live params session", delegate { RigTests.Live(live, Check, python, Path.GetDirectoryName(Path.GetDirectoryName(Path.GetFullPath(vectors))), 180); });
            if (Failures.Count > 0)
            {
                Console.WriteLine();
                Console.WriteLine("Failures:");
                foreach (string f in Failures) Console.WriteLine("  " + f.Split('\n')[0]);
            }
            Console.WriteLine(_passed + " passed, " + _failed + " failed");
            return _failed == 0 ? 0 : 1;
        }

        // ============================================================ golden vectors

        static Dictionary<string, object> LoadVector(string dir, string name)
        {
            return J.O(Json.Parse(File.ReadAllText(Path.Combine(dir, name + ".json"))));
        }

        internal static FrameFormat FormatFromJson(Dictionary<string, object> f)
        {
            FrameEncoding e;
            Protocol.TryParseEncoding((string)f["encoding"], out e);
            Quant q = null;
            if (J.Has(f, "quant"))
            {
                Dictionary<string, object> qj = J.O(f["quant"]);
                q = new Quant();
                double[] a = J.Flat(qj["pos_min"]), b = J.Flat(qj["pos_max"]), c = J.Flat(qj["log_scale"]);
                for (int i = 0; i < 3; i++) { q.PosMin[i] = (float)a[i]; q.PosMax[i] = (float)b[i]; }
                q.LogScale[0] = (float)c[0]; q.LogScale[1] = (float)c[1];
            }
            return new FrameFormat(e, (int)J.I(f["count"]), J.Has(f, "sparse") && (bool)f["sparse"], q);
        }

        static void VectorTests(string dir)
        {
            string[] files = Directory.GetFiles(dir, "*.json");
            Array.Sort(files, StringComparer.Ordinal);
            Check(files.Length > 0, "golden vectors found in " + dir, files.Length + " files");
            foreach (string path in files)
            {
                string name = Path.GetFileNameWithoutExtension(path);
                if (name == "tables") continue; // the protocol's tables, not a vector: TableTests
                if (name == "rig_tiny_frames") continue; // rig_tiny's deformed frames, not a message: RigTests.Frames
                Run("vector " + name, delegate { OneVector(dir, name); });
            }
        }

        // ============================================================ the protocol's tables (vectors/tables.json)

        /// <summary>This client's copies of the protocol's tables (Protocol.cs, Layouts.cs) against tables.json,
        /// which protocol/make_vectors.py writes from the one Python source (ofera_protocol.tables).</summary>
        static List<string> Keys(Dictionary<string, object> d) { return (List<string>)d["\u0000order"]; }

        static void TableTests(string dir)
        {
            Dictionary<string, object> t = J.O(Json.Parse(File.ReadAllText(Path.Combine(dir, "tables.json"))));
            Check(J.I(t["protocol"]) == Protocol.Version && (string)t["endpoint"] == Protocol.Endpoint,
                  "tables: protocol version and endpoint");
            Dictionary<string, object> layouts = J.O(t["layouts"]);
            Check(string.Join(",", Protocol.Layouts) == string.Join(",", Keys(layouts)), "tables: layout names",
                  string.Join(",", Protocol.Layouts) + " vs " + string.Join(",", Keys(layouts)));
            foreach (string name in Keys(layouts))
            {
                Dictionary<string, object> lay = J.O(layouts[name]);
                List<string> want = new List<string>();
                foreach (object n in J.L(lay["names"])) want.Add((string)n);
                string[] got = Layouts.Names(name);
                Check(Protocol.LayoutLength(name) == J.I(lay["length"]) && got != null
                      && string.Join(",", got) == string.Join(",", want), "tables: layout " + name,
                      got == null ? "unknown to Layouts.Names" : got.Length + " names");
            }
            Dictionary<string, object> encodings = J.O(t["encodings"]);
            Check(string.Join(",", Protocol.Encodings) == string.Join(",", Keys(encodings)), "tables: encoding names");
            foreach (string name in Keys(encodings))
            {
                Dictionary<string, object> e = J.O(encodings[name]);
                FrameEncoding fe;
                bool known = Protocol.TryParseEncoding(name, out fe);
                int p = 0, r = 0, sc = 0;
                if (known) Protocol.FieldBytes(fe, out p, out r, out sc);
                Check(known && Protocol.EncodingName(fe) == name && p == J.I(e["position"]) && r == J.I(e["rotation"])
                      && sc == J.I(e["scale"]) && p + r + sc == J.I(e["bytes_per_gaussian"]), "tables: field sizes of " + name,
                      p + "+" + r + "+" + sc);
            }
            List<string> coords = new List<string>();
            foreach (object c in J.L(t["coords"])) coords.Add((string)c);
            Check(string.Join(",", Protocol.CoordsNames) == string.Join(",", coords), "tables: coords");
            Dictionary<string, object> errors = J.O(t["errors"]);
            List<string> declared = new List<string>();
            foreach (System.Reflection.FieldInfo f in typeof(ErrorCodes).GetFields())
                if (f.IsLiteral && f.FieldType == typeof(string)) declared.Add((string)f.GetRawConstantValue());
            declared.Sort(StringComparer.Ordinal);
            List<string> codes = new List<string>(Keys(errors));
            codes.Sort(StringComparer.Ordinal);
            Check(string.Join(",", declared) == string.Join(",", codes), "tables: error codes",
                  string.Join(",", declared) + " vs " + string.Join(",", codes));
            foreach (string code in Keys(errors))
            {
                Dictionary<string, object> e = J.O(errors[code]);
                string fatality = (string)e["fatality"];
                bool closeOk = !J.Has(e, "close_code") ? fatality == "never" : ErrorCodes.CloseCode(code) == J.I(e["close_code"]);
                Check(ErrorCodes.AlwaysFatal(code) == (fatality == "always") && closeOk
                      && new ProtocolException(code, "x").Fatal == (fatality == "always"), "tables: error " + code, fatality);
            }
            Check(ErrorCodes.CloseCode("not_a_v1_code") == J.I(J.O(t["close_codes"])["unknown_fatal"]),
                  "tables: close code of an unknown fatal error");
            Dictionary<string, object> lim = J.O(t["limits"]);
            Check(J.I(lim["max_client_message"]) == Protocol.MaxClientMessage && J.I(lim["max_server_message"]) == Protocol.MaxServerMessage
                  && J.I(lim["max_depth"]) == Protocol.MaxDepth && J.I(lim["max_container_len"]) == Protocol.MaxContainerLength
                  && J.I(lim["max_str_len"]) == Protocol.MaxStringBytes && J.I(lim["max_id_len"]) == Protocol.MaxIdLength
                  && J.I(lim["max_timing_stages"]) == Protocol.MaxTimingStages && J.I(lim["max_sh_degree"]) == Protocol.MaxShDegree,
                  "tables: limits");
        }

        static void OneVector(string dir, string name)
        {
            Dictionary<string, object> v = LoadVector(dir, name);
            byte[] bytes = Hex((string)v["hex"]);
            byte[] file = File.ReadAllBytes(Path.Combine(dir, name + ".msgpack"));
            if (ToHex(file, 0, file.Length) != ToHex(bytes, 0, bytes.Length) || bytes.Length != J.I(v["size"]))
            {
                Check(false, "vector " + name, ".msgpack file differs from the JSON's hex/size");
                return;
            }
            if (DeltaTests.Handles(name, v)) { DeltaTests.Vector(dir, name, v, Check); return; } // PROTOCOL.md 7.1
            if (RigTests.Handles(name, v)) { RigTests.Vector(dir, name, v, Check); return; } // PROTOCOL.md 13
            if (RoomTests.Handles(name)) { RoomTests.Vector(dir, name, v, Check); return; } // PROTOCOL.md 12
            bool toServer = (string)v["direction"] == "client_to_server";
            if (J.Has(v, "expect_error"))
            {
                string want = (string)J.O(v["expect_error"])["code"];
                Dictionary<string, object> ctx = J.Has(v, "context") ? J.O(v["context"]) : new Dictionary<string, object>();
                string got = "(no error)";
                try
                {
                    if (toServer)
                    {
                        string layout = J.Has(ctx, "layout") ? (string)ctx["layout"] : null;
                        new ClientMessageDecoder().Decode(bytes, 0, bytes.Length, layout, new ClientMessage());
                    }
                    else
                    {
                        FrameFormat fmt = J.Has(ctx, "format") ? FormatFromJson(J.O(ctx["format"])) : null;
                        new ServerMessageDecoder().Decode(bytes, 0, bytes.Length, fmt, new ServerMessage());
                    }
                }
                catch (ProtocolException e) { got = e.Code + " (" + e.Detail + ")"; }
                Check(got.StartsWith(want + " ("), "vector " + name + " -> error " + want, "got " + got);
                return;
            }
            Dictionary<string, object> fields = J.O(v["fields"]);
            string type = (string)v["type"];
            if (toServer) ClientVector(name, bytes, fields, type);
            else ServerVector(name, bytes, fields, type, v);
        }

        static void ClientVector(string name, byte[] bytes, Dictionary<string, object> f, string type)
        {
            ClientMessage m = new ClientMessage();
            ClientMessageKind kind = new ClientMessageDecoder().Decode(bytes, 0, bytes.Length, null, m);
            MsgPackWriter w = new MsgPackWriter(64);
            string problems = "";
            switch (type)
            {
                case "hello":
                    {
                        Hello h = m.Hello;
                        if (kind != ClientMessageKind.Hello) problems += " kind " + kind;
                        if (h.Protocol != J.I(f["protocol"])) problems += " protocol";
                        if (h.Layout != (string)f["layout"]) problems += " layout";
                        if (h.Avatar != (J.Has(f, "avatar") ? (string)f["avatar"] : "default")) problems += " avatar";
                        if (h.Encoding != (J.Has(f, "encoding") ? (string)f["encoding"] : "f32")) problems += " encoding";
                        if (h.Coords != (J.Has(f, "coords") ? (string)f["coords"] : "flame")) problems += " coords";
                        if (h.Sparse != (J.Has(f, "sparse") ? (bool)f["sparse"] : false)) problems += " sparse";
                        if (h.Device != (J.Has(f, "device") ? (string)f["device"] : null)) problems += " device";
                        if (h.Token != (J.Has(f, "token") ? (string)f["token"] : null)) problems += " token";
                        if (h.MaxGaussians != (J.Has(f, "max_gaussians") ? (long?)J.I(f["max_gaussians"]) : null)) problems += " max_gaussians";
                        // re-encode from the JSON fields: must give the same bytes
                        Hello e = new Hello();
                        e.Protocol = (int)J.I(f["protocol"]);
                        e.Layout = (string)f["layout"];
                        e.Avatar = J.Has(f, "avatar") ? (string)f["avatar"] : null;
                        e.Encoding = J.Has(f, "encoding") ? (string)f["encoding"] : null;
                        e.Coords = J.Has(f, "coords") ? (string)f["coords"] : null;
                        e.Sparse = J.Has(f, "sparse") ? (bool?)(bool)f["sparse"] : null;
                        e.Device = J.Has(f, "device") ? (string)f["device"] : null;
                        e.Token = J.Has(f, "token") ? (string)f["token"] : null;
                        e.MaxGaussians = J.Has(f, "max_gaussians") ? (long?)J.I(f["max_gaussians"]) : null;
                        ClientMessageEncoder.Hello(w, e);
                        break;
                    }
                case "bs":
                    {
                        double[] want = J.Values(J.O(f["w"]));
                        if (kind != ClientMessageKind.Blendshapes || m.Blendshapes.Seq != J.I(f["seq"]) || m.Blendshapes.T != J.I(f["t"]) || m.Blendshapes.Count != want.Length)
                            problems += " header";
                        string c = Compare(m.Blendshapes.W, 0, want, 0, 0);
                        if (c != null) problems += " w " + c;
                        float[] wf = new float[want.Length];
                        for (int i = 0; i < wf.Length; i++) wf[i] = (float)want[i];
                        if (J.Has(f, "conf"))
                        {
                            // Optional bs.conf (PROTOCOL.md 4.2): this client does not send it yet; its decoder must
                            // accept the message (unknown keys are ignored) with the weights intact.
                            Check(problems.Length == 0, "vector " + name + " decodes (conf ignored)", problems);
                            return;
                        }
                        ClientMessageEncoder.Bs(w, J.I(f["seq"]), J.I(f["t"]), wf, wf.Length);
                        break;
                    }
                case "ping":
                    if (kind != ClientMessageKind.Ping || m.PingT != J.I(f["t"])) problems += " t";
                    ClientMessageEncoder.Ping(w, J.I(f["t"]));
                    break;
                case "bye":
                    if (kind != ClientMessageKind.Bye) problems += " kind";
                    ClientMessageEncoder.Bye(w);
                    break;
            }
            Check(problems.Length == 0, "vector " + name + " decodes to its JSON", problems);
            Check(ToHex(w.Buffer, 0, w.Length) == ToHex(bytes, 0, bytes.Length), "vector " + name + " re-encodes byte-identical",
                  ToHex(w.Buffer, 0, w.Length));
        }

        static void ServerVector(string name, byte[] bytes, Dictionary<string, object> f, string type, Dictionary<string, object> v)
        {
            FrameFormat fmt = J.Has(v, "format") ? FormatFromJson(J.O(v["format"])) : null;
            ServerMessage m = new ServerMessage();
            ServerMessageDecoder dec = new ServerMessageDecoder();
            ServerMessageKind kind = dec.Decode(bytes, 0, bytes.Length, fmt, m);
            string problems = "";
            switch (type)
            {
                case "welcome":
                    {
                        Welcome w = m.Welcome;
                        Dictionary<string, object> av = J.O(f["avatar"]);
                        if (kind != ServerMessageKind.Welcome) problems += " kind";
                        if (w.Protocol != J.I(f["protocol"]) || w.Session != (string)f["session"]) problems += " protocol/session";
                        if (w.AvatarId != (string)av["id"] || w.Count != J.I(av["count"]) || w.ShDegree != J.I(av["sh_degree"])) problems += " avatar";
                        if (w.Layout != (string)f["layout"] || w.Encoding != (string)f["encoding"] || w.Coords != (string)f["coords"]) problems += " layout/encoding/coords";
                        if (w.Sparse != (bool)f["sparse"]) problems += " sparse";
                        if (w.Server != (J.Has(f, "server") ? (string)f["server"] : null)) problems += " server";
                        if (J.Has(f, "quant"))
                        {
                            Dictionary<string, object> q = J.O(f["quant"]);
                            if (w.Quant == null) problems += " quant missing";
                            else
                            {
                                string c = Compare(w.Quant.PosMin, 0, J.Values(J.O(q["pos_min"])), 0, 0)
                                           ?? Compare(w.Quant.PosMax, 0, J.Values(J.O(q["pos_max"])), 0, 0)
                                           ?? Compare(w.Quant.LogScale, 0, J.Values(J.O(q["log_scale"])), 0, 0);
                                if (c != null) problems += " quant " + c;
                            }
                        }
                        else if (w.Quant != null) problems += " unexpected quant";
                        break;
                    }
                case "avatar":
                    {
                        AvatarChunkHeader h = m.Avatar;
                        if (kind != ServerMessageKind.Avatar) problems += " kind";
                        if (h.Count != J.I(f["count"]) || h.ShDegree != J.I(f["sh_degree"]) || h.Chunk != J.I(f["chunk"]) ||
                            h.Chunks != J.I(f["chunks"]) || h.Offset != J.I(f["offset"]) || h.N != J.I(f["n"])) problems += " header";
                        AvatarData a = new AvatarData(h.Count, h.ShDegree);
                        dec.CopyAvatarChunk(bytes, a);
                        string c = Compare(a.Opacity, h.Offset, J.Values(J.O(f["opacity"])), 0, 0);
                        if (c != null) problems += " opacity " + c;
                        c = Compare(a.Sh, h.Offset * a.K * 3, J.Values(J.O(f["sh"])), 0, 0);
                        if (c != null) problems += " sh " + c;
                        c = Compare(a.Position, h.Offset * 3, J.Values(J.O(f["position"])), 0, 0);
                        if (c != null) problems += " position " + c;
                        c = Compare(a.Rotation, h.Offset * 4, J.Values(J.O(f["rotation"])), 0, 0);
                        if (c != null) problems += " rotation " + c;
                        c = Compare(a.Scale, h.Offset * 3, J.Values(J.O(f["scale"])), 0, 0);
                        if (c != null) problems += " scale " + c;
                        break;
                    }
                case "frame":
                    {
                        FrameData fr = m.Frame;
                        if (kind != ServerMessageKind.Frame) problems += " kind";
                        if (fr.Seq != J.I(f["seq"]) || fr.T != J.I(f["t"]) || fr.N != J.I(f["n"])) problems += " seq/t/n";
                        Dictionary<string, object> timing = J.O(f["timing"]);
                        List<string> order = (List<string>)timing["\u0000order"];
                        if (fr.TimingCount != order.Count) problems += " timing count";
                        for (int i = 0; i < order.Count && i < fr.TimingCount; i++)
                            if (fr.TimingNames[i] != order[i] || fr.TimingValues[i] != J.I(timing[order[i]])) problems += " timing " + order[i];
                        if (J.Has(f, "index"))
                        {
                            double[] idx = J.Values(J.O(f["index"]));
                            if (!fr.HasIndex || idx.Length != fr.N) problems += " index missing";
                            else for (int i = 0; i < idx.Length; i++) if (fr.Index[i] != (uint)idx[i]) problems += " index[" + i + "]";
                        }
                        else if (fr.HasIndex) problems += " unexpected index";
                        Dictionary<string, object> dj = J.O(v["decoded"]);
                        // every encoding decodes bit-exactly to the reference's float32 values
                        double rel = 0;
                        double abs = 0;
                        string c = Compare(fr.Position, 0, J.Flat(dj["position"]), abs, rel);
                        if (c != null) problems += " position " + c;
                        c = Compare(fr.Rotation, 0, J.Flat(dj["rotation"]), abs, rel);
                        if (c != null) problems += " rotation " + c;
                        c = Compare(fr.Scale, 0, J.Flat(dj["scale"]), abs, rel);
                        if (c != null) problems += " scale " + c;
                        break;
                    }
                case "error":
                    {
                        ErrorMessage e = m.Error;
                        if (kind != ServerMessageKind.Error || e.Code != (string)f["code"] || e.Message != (string)f["message"] || e.Fatal != (bool)f["fatal"]) problems += " fields";
                        long? seq = J.Has(f, "seq") ? (long?)J.I(f["seq"]) : null;
                        if (e.Seq != seq) problems += " seq";
                        break;
                    }
                case "pong":
                    if (kind != ServerMessageKind.Pong || m.PongT != J.I(f["t"])) problems += " t";
                    break;
                default:
                    problems += " unknown type " + type;
                    break;
            }
            Check(problems.Length == 0, "vector " + name + " decodes to its JSON", problems);
        }

        // ============================================================ session flows on the vectors

        static byte[] VectorBytes(string dir, string name) { return File.ReadAllBytes(Path.Combine(dir, name + ".msgpack")); }

        static void SessionTests(string dir)
        {
            Run("q13 encoder vs vectors", delegate
            {
                // the protocol's smallest-three encoder (6.3), applied to frame_f32's rotations, gives frame_q13's words
                double[] rot = J.Values(J.O(J.O(LoadVector(dir, "frame_f32")["fields"])["rotation"]));
                double[] words = J.Values(J.O(J.O(LoadVector(dir, "frame_q13")["fields"])["rotation"]));
                bool same = true;
                for (int g = 0; g < words.Length; g++)
                    if (FrameCodec.PackSmallestThree((float)rot[4 * g], (float)rot[4 * g + 1], (float)rot[4 * g + 2], (float)rot[4 * g + 3]) != (uint)words[g]) same = false;
                Check(same, "q13: C# smallest-three encoder reproduces frame_q13's rotation words");
            });
            Run("session: dense f32 (welcome, 2 avatar chunks, frame)", delegate
            {
                ClientConnection c = new ClientConnection();
                MsgPackWriter w = new MsgPackWriter();
                Hello h = new Hello(); h.Layout = "arkit52";
                c.EncodeHello(h, w);
                ServerMessage m = new ServerMessage();
                byte[] b = VectorBytes(dir, "welcome");
                c.Receive(b, 0, b.Length, m);
                Check(c.State == ClientState.ReceivingAvatar, "session: welcome -> receiving avatar", c.State.ToString());
                string err = "(none)";
                try { byte[] fb = VectorBytes(dir, "frame_f32"); c.Receive(fb, 0, fb.Length, m); }
                catch (ProtocolException e) { err = e.Code + (e.Fatal ? " fatal" : ""); }
                Check(err == "not_ready fatal" && c.State == ClientState.Closed, "session: frame before the avatar is fatal not_ready", err);

                c = new ClientConnection();
                c.EncodeHello(h, w);
                c.Receive(b, 0, b.Length, m);
                foreach (string chunk in new[] { "avatar_chunk0", "avatar_chunk1" })
                {
                    byte[] cb = VectorBytes(dir, chunk);
                    c.Receive(cb, 0, cb.Length, m);
                }
                Check(c.State == ClientState.Streaming, "session: two chunks -> streaming", c.State.ToString());
                Dictionary<string, object> whole = J.O(LoadVector(dir, "avatar")["fields"]);
                string cmp = Compare(c.Avatar.Position, 0, J.Values(J.O(whole["position"])), 0, 0)
                             ?? Compare(c.Avatar.Sh, 0, J.Values(J.O(whole["sh"])), 0, 0)
                             ?? Compare(c.Avatar.Opacity, 0, J.Values(J.O(whole["opacity"])), 0, 0)
                             ?? Compare(c.Avatar.Rotation, 0, J.Values(J.O(whole["rotation"])), 0, 0)
                             ?? Compare(c.Avatar.Scale, 0, J.Values(J.O(whole["scale"])), 0, 0);
                Check(cmp == null, "session: assembled chunks equal the one-chunk avatar", cmp);
                GaussianState st = new GaussianState(c.Avatar);
                m.Frame = new FrameData();
                byte[] f32 = VectorBytes(dir, "frame_f32");
                c.Receive(f32, 0, f32.Length, m);
                Check(st.Apply(m.Frame), "session: dense frame applies");
                err = "(none)";
                try { byte[] sp = VectorBytes(dir, "frame_f32_sparse"); c.Receive(sp, 0, sp.Length, m); }
                catch (ProtocolException e) { err = e.Code + (e.Fatal ? " fatal" : " non-fatal"); }
                Check(err == "bad_field non-fatal" && c.State == ClientState.Streaming, "session: index in a dense session is a non-fatal bad_field", err + " " + c.State);
                c.Receive(f32, 0, f32.Length, m);
                Check(m.Frame.Seq == 42, "session: goes on after a bad frame");
                err = "(none)";
                try { byte[] ab = VectorBytes(dir, "avatar"); c.Receive(ab, 0, ab.Length, m); }
                catch (ProtocolException e) { err = e.Code + (e.Fatal ? " fatal" : ""); }
                Check(err == "not_ready fatal", "session: avatar while streaming is fatal", err);
            });

            Run("session: q13 sparse unity", delegate
            {
                ClientConnection c = new ClientConnection();
                MsgPackWriter w = new MsgPackWriter();
                Hello h = new Hello(); h.Layout = "ovr63"; h.Coords = "unity"; h.Encoding = "q13"; h.Sparse = true;
                c.EncodeHello(h, w);
                ServerMessage m = new ServerMessage();
                byte[] b = VectorBytes(dir, "welcome_q13");
                c.Receive(b, 0, b.Length, m);
                byte[] ab = VectorBytes(dir, "avatar");
                c.Receive(ab, 0, ab.Length, m);
                Check(c.State == ClientState.Streaming && c.Format.Encoding == FrameEncoding.Q13 && c.Format.Sparse, "session q13: streaming with q13 sparse format");
                GaussianState st = new GaussianState(c.Avatar);
                st.ClearDirty();
                byte[] fb = VectorBytes(dir, "frame_q13_sparse");
                m.Frame = new FrameData();
                c.Receive(fb, 0, fb.Length, m);
                st.Apply(m.Frame);
                Dictionary<string, object> dense = J.O(LoadVector(dir, "frame_q13")["decoded"]);
                Dictionary<string, object> neutral = J.O(LoadVector(dir, "avatar")["fields"]);
                double[] dp = J.Flat(dense["position"]), np = J.Values(J.O(neutral["position"]));
                // Gaussians 1 and 3 from the sparse frame, 0 and 2 neutral
                double[] want = new double[12];
                for (int g = 0; g < 4; g++)
                    for (int k = 0; k < 3; k++)
                        want[3 * g + k] = (g == 1 || g == 3) ? dp[3 * g + k] : np[3 * g + k];
                string cmp = Compare(st.Position, 0, want, 1e-9, 2.5e-7);
                Check(cmp == null && st.DirtyMin == 1 && st.DirtyMax == 3, "session q13: sparse frame updates Gaussians 1 and 3 only", cmp + " dirty " + st.DirtyMin + ".." + st.DirtyMax);

                ClientConnection c2 = new ClientConnection();
                Hello h2 = new Hello(); h2.Layout = "ovr63"; h2.Coords = "flame";
                c2.EncodeHello(h2, w);
                string err = "(none)";
                try { c2.Receive(b, 0, b.Length, m); }
                catch (ProtocolException e) { err = e.Code + (e.Fatal ? " fatal" : ""); }
                Check(err == "bad_field fatal", "session: welcome with other coords than asked is fatal", err);
            });

            Run("session: error messages", delegate
            {
                ClientConnection c = new ClientConnection();
                MsgPackWriter w = new MsgPackWriter();
                Hello h = new Hello(); h.Layout = "arkit52";
                c.EncodeHello(h, w);
                ServerMessage m = new ServerMessage();
                byte[] e1 = VectorBytes(dir, "error");
                c.Receive(e1, 0, e1.Length, m);
                Check(c.State == ClientState.AwaitingWelcome && !m.Error.Fatal, "session: non-fatal error keeps the state");
                byte[] e2 = VectorBytes(dir, "error_fatal");
                c.Receive(e2, 0, e2.Length, m);
                Check(c.State == ClientState.Closed && m.Error.Fatal && ErrorCodes.CloseCode(m.Error.Code) == 4010, "session: fatal error closes (close code 4010)");
            });
        }

        // ============================================================ unit tests

        /// <summary>The payload of bin field `key` in a msgpack message (found by its key; test helper).</summary>
        static byte[] BinOf(byte[] msg, string key)
        {
            byte[] k = Encoding.ASCII.GetBytes(key);
            for (int i = 0; i + 1 + k.Length + 2 < msg.Length; i++)
            {
                if (msg[i] != (byte)(0xa0 | k.Length)) continue;
                int j = 0;
                while (j < k.Length && msg[i + 1 + j] == k[j]) j++;
                if (j < k.Length) continue;
                int o = i + 1 + k.Length, len, start;
                if (msg[o] == 0xc4) { len = msg[o + 1]; start = o + 2; }
                else if (msg[o] == 0xc5) { len = (msg[o + 1] << 8) | msg[o + 2]; start = o + 3; }
                else continue;
                byte[] r = new byte[len];
                Buffer.BlockCopy(msg, start, r, 0, len);
                return r;
            }
            return null;
        }

        static void PayloadTests(string dir)
        {
            Run("gpu payload: wire arrays kept as they arrived", delegate
            {
                foreach (string name in new[] { "frame_f32", "frame_f32_sparse", "frame_f16", "frame_f16_sparse", "frame_q13", "frame_q13_sparse" })
                {
                    Dictionary<string, object> v = LoadVector(dir, name);
                    FrameFormat fmt = FormatFromJson(J.O(v["format"]));
                    byte[] b = VectorBytes(dir, name);
                    foreach (bool values in new[] { true, false })
                    {
                        ServerMessageDecoder d = new ServerMessageDecoder();
                        d.KeepPayload = true;
                        d.DecodeValues = values;
                        ServerMessage m = new ServerMessage();
                        m.Frame = new FrameData();
                        d.Decode(b, 0, b.Length, fmt, m);
                        FramePayload p = m.Frame.Payload;
                        string problems = "";
                        if (m.Frame.HasValues != values) problems += " HasValues";
                        string[] keys = { "index", "position", "rotation", "scale" };
                        int[] words = { p.IndexWord, p.PositionWord, p.RotationWord, p.ScaleWord };
                        int end = 0;
                        for (int k = 0; k < 4; k++)
                        {
                            byte[] bin = BinOf(b, keys[k]);
                            if (bin == null) { if (k == 0 && p.HasIndex) problems += " index missing"; continue; }
                            if (4 * words[k] != end) problems += " " + keys[k] + " not at the padded end of the previous section";
                            for (int i = 0; i < bin.Length; i++) if (p.Bytes[4 * words[k] + i] != bin[i]) { problems += " " + keys[k] + " byte " + i; break; }
                            end = 4 * words[k] + ((bin.Length + 3) & ~3);
                            for (int i = 4 * words[k] + bin.Length; i < end; i++) if (p.Bytes[i] != 0) problems += " padding";
                        }
                        if (p.Length != end || p.Length % 4 != 0) problems += " length " + p.Length + " != " + end;
                        if (p.N != m.Frame.N || p.Encoding != fmt.Encoding || p.HasIndex != m.Frame.HasIndex) problems += " header";
                        Check(problems.Length == 0, "gpu payload: " + name + (values ? " (with float decode)" : " (payload only)"), problems);
                    }
                }
                byte[] nan = VectorBytes(dir, "invalid_frame_nan");
                FrameFormat f32 = FormatFromJson(J.O(J.O(LoadVector(dir, "invalid_frame_nan")["context"])["format"]));
                ServerMessageDecoder pd = new ServerMessageDecoder();
                pd.KeepPayload = true; pd.DecodeValues = false;
                string got = "(none)";
                try { pd.Decode(nan, 0, nan.Length, f32, new ServerMessage { Frame = new FrameData() }); }
                catch (ProtocolException e) { got = e.Code; }
                Check(got == "non_finite", "gpu payload: payload-only decoding still refuses NaN (non_finite)", got);
                // f16: a half with an all-ones exponent
                Dictionary<string, object> hv = LoadVector(dir, "frame_f16");
                FrameFormat f16 = FormatFromJson(J.O(hv["format"]));
                byte[] hb = VectorBytes(dir, "frame_f16");
                byte[] pos = BinOf(hb, "position");
                int at = -1;
                for (int i = 0; i + pos.Length <= hb.Length && at < 0; i++)
                {
                    int j = 0;
                    while (j < pos.Length && hb[i + j] == pos[j]) j++;
                    if (j == pos.Length) at = i;
                }
                hb[at + 1] = 0x7c; // first half -> +inf
                got = "(none)";
                try { pd.Decode(hb, 0, hb.Length, f16, new ServerMessage { Frame = new FrameData() }); }
                catch (ProtocolException e) { got = e.Code; }
                Check(got == "non_finite", "gpu payload: payload-only f16 decoding refuses infinity", got);
            });

            Run("gpu reference: WriteFrame matches the state path; neutral payload", delegate
            {
                ClientConnection c = new ClientConnection();
                MsgPackWriter w = new MsgPackWriter();
                Hello h = new Hello(); h.Layout = "arkit52";
                c.EncodeHello(h, w);
                ServerMessage m = new ServerMessage();
                m.Frame = new FrameData();
                foreach (string n in new[] { "welcome", "avatar" }) { byte[] b = VectorBytes(dir, n); c.Receive(b, 0, b.Length, m); }
                byte[] fb = VectorBytes(dir, "frame_f32");
                c.Receive(fb, 0, fb.Length, m);
                GaussianState st = new GaussianState(c.Avatar);
                st.Apply(m.Frame);
                int[] map = { 2, -1, 0, 4 }; // splat 1 and 3 unmatched, server 1 has no splat
                float[] fpos = new float[15]; uint[] fother = new uint[20];
                int lo, hi;
                UgsPacking.WriteGpu(st, 0, 3, map, true, fpos, fother, out lo, out hi);
                uint[] pos = new uint[15], other = new uint[20];
                UgsPacking.Hide(pos, other, 5);
                UgsPacking.WriteFrame(m.Frame, map, true, pos, other);
                bool same = true;
                foreach (int g in new[] { 0, 2, 4 })
                {
                    for (int k = 0; k < 3; k++) if (pos[3 * g + k] != BitCast.FloatToUInt(fpos[3 * g + k])) same = false;
                    for (int k = 0; k < 4; k++) if (other[4 * g + k] != fother[4 * g + k]) same = false;
                }
                bool hidden = pos[3] == UgsPacking.HiddenPositionBits && pos[9] == UgsPacking.HiddenPositionBits && other[5] == 0 && other[13] == 0 &&
                              other[4] == UgsPacking.PackRotation(0f, 0f, 0f, 1f);
                Check(same && hidden, "gpu reference: WriteFrame (mirrored) = WriteGpu for matched splats; unmatched stay hidden (NaN position, zero scale)");
                FramePayload np = new FramePayload();
                GpuTables.NeutralPayload(c.Avatar, np);
                bool ok = np.N == 4 && !np.HasIndex && np.PositionWord == 0 && np.RotationWord == 12 && np.ScaleWord == 28 && np.Words == 40 &&
                          BitCast.ReadFloatLE(np.Bytes, 4 * 12 + 4 * 7) == c.Avatar.Rotation[7] && BitCast.ReadFloatLE(np.Bytes, 4 * 28 + 4 * 11) == c.Avatar.Scale[11];
                Check(ok, "gpu payload: the avatar's neutral state as a dense f32 payload");
                uint[] permWords = GpuTables.PermutationWords(map);
                Check(permWords[1] == 0xffffffffu && permWords[3] == 4 && GpuTables.KernelName(FrameEncoding.F16) == "CSOferaDecodeF16",
                      "gpu tables: permutation words (0xffffffff unmatched) and kernel names");
            });
        }

        static void UnitTests(string python)
        {
            Run("msgpack", MsgPackTests);
            Run("half", delegate
            {
                int bad = 0;
                for (int h = 0; h < 65536; h++)
                {
                    if (!Half.IsFinite((ushort)h)) continue;
                    ushort back = Half.FromFloat(Half.ToFloat((ushort)h));
                    if (back != h && !(Half.ToFloat((ushort)h) == 0f && (back & 0x7fff) == 0)) bad++;
                }
                Check(bad == 0, "f16: every finite half round-trips through float32", bad + " mismatches");
                Check(Half.ToFloat(0x3c00) == 1f && Half.ToFloat(0xc000) == -2f && Half.ToFloat(0x0001) == 5.9604645e-8f && Half.ToFloat(0x7bff) == 65504f,
                      "f16: known values (1, -2, smallest subnormal, 65504)");
            });
            Run("q13 rotations", delegate
            {
                Random r = new Random(7);
                float[] q = new float[4];
                double worst = 0;
                for (int i = 0; i < 20000; i++)
                {
                    double x = r.NextDouble() * 2 - 1, y = r.NextDouble() * 2 - 1, z = r.NextDouble() * 2 - 1, ww = r.NextDouble() * 2 - 1;
                    double n = Math.Sqrt(x * x + y * y + z * z + ww * ww);
                    x /= n; y /= n; z /= n; ww /= n;
                    FrameCodec.UnpackSmallestThree(FrameCodec.PackSmallestThree((float)x, (float)y, (float)z, (float)ww), q, 0);
                    double d1 = Math.Sqrt(Sq(q[0] - x) + Sq(q[1] - y) + Sq(q[2] - z) + Sq(q[3] - ww));
                    double d2 = Math.Sqrt(Sq(q[0] + x) + Sq(q[1] + y) + Sq(q[2] + z) + Sq(q[3] + ww));
                    worst = Math.Max(worst, Math.Min(d1, d2));
                }
                Check(worst <= 2.8e-3, "q13: smallest-three round trip within the spec's 2.8e-3", "worst " + worst);
                FrameCodec.UnpackSmallestThree(FrameCodec.PackSmallestThree(0, 0, 0, 1), q, 0);
                Check(q[0] == 0 && q[1] == 0 && q[2] == 0 && q[3] == 1, "q13: identity is exact");
            });
            Run("ugs packing", delegate
            {
                Random r = new Random(3);
                float[] q = new float[4];
                double worst = 0;
                for (int i = 0; i < 20000; i++)
                {
                    double x = r.NextDouble() * 2 - 1, y = r.NextDouble() * 2 - 1, z = r.NextDouble() * 2 - 1, ww = r.NextDouble() * 2 - 1;
                    double n = Math.Sqrt(x * x + y * y + z * z + ww * ww);
                    x /= n; y /= n; z /= n; ww /= n;
                    UgsPacking.UnpackRotation(UgsPacking.PackRotation((float)x, (float)y, (float)z, (float)ww), q, 0);
                    double d1 = Math.Sqrt(Sq(q[0] - x) + Sq(q[1] - y) + Sq(q[2] - z) + Sq(q[3] - ww));
                    double d2 = Math.Sqrt(Sq(q[0] + x) + Sq(q[1] + y) + Sq(q[2] + z) + Sq(q[3] + ww));
                    worst = Math.Max(worst, Math.Min(d1, d2));
                }
                Check(worst <= 4e-3, "UnityGaussianSplatting 10.10.10.2 rotation packing round-trips (shader decode)", "worst " + worst);
            });
            Run("permutation", delegate
            {
                Random r = new Random(11);
                int n = 5000;
                float[] server = new float[3 * n];
                for (int i = 0; i < 3 * n; i++) server[i] = (float)(r.NextDouble() * 0.3 - 0.15);
                int[] perm = new int[n];
                for (int i = 0; i < n; i++) perm[i] = i;
                for (int i = n - 1; i > 0; i--) { int j = r.Next(i + 1); int t = perm[i]; perm[i] = perm[j]; perm[j] = t; }
                foreach (bool mirrored in new[] { false, true })
                {
                    float[] gpu = new float[3 * n];
                    for (int i = 0; i < n; i++)
                    {
                        gpu[3 * perm[i]] = mirrored ? -server[3 * i] : server[3 * i];
                        gpu[3 * perm[i] + 1] = server[3 * i + 1];
                        gpu[3 * perm[i] + 2] = server[3 * i + 2];
                    }
                    bool mx; int unmatched;
                    int[] map = SplatPermutation.Build(server, n, gpu, n, 1e-6f, out mx, out unmatched);
                    int wrong = 0;
                    for (int i = 0; i < n; i++) if (map[i] != perm[i]) wrong++;
                    Check(wrong == 0 && unmatched == 0 && mx == mirrored, "server->GPU permutation recovered" + (mirrored ? " (x-mirrored asset)" : ""), wrong + " wrong, " + unmatched + " unmatched, mirror " + mx);
                }
            });
            Run("gpu writer", delegate
            {
                AvatarData a = new AvatarData(3, 0);
                for (int i = 0; i < 9; i++) { a.Position[i] = i * 0.01f; a.Scale[i] = 0.001f * (i + 1); }
                for (int g = 0; g < 3; g++) { a.Rotation[4 * g + 3] = 1f; }
                a.Rotation[4] = 0.6f; a.Rotation[7] = 0.8f; // Gaussian 1: (0.6, 0, 0, 0.8)
                GaussianState st = new GaussianState(a);
                int[] map = { 2, 0, 1 };
                float[] pos = new float[9]; uint[] other = new uint[12];
                int lo, hi;
                UgsPacking.WriteGpu(st, 0, 2, map, false, pos, other, out lo, out hi);
                float[] q = new float[4];
                UgsPacking.UnpackRotation(other[0], q, 0); // GPU 0 holds server Gaussian 1
                bool ok = lo == 0 && hi == 2 && pos[0] == a.Position[3] && pos[6] == a.Position[0] && BitCast.UIntToFloat(other[4 * 2 + 1]) == a.Scale[0] &&
                          Math.Abs(Math.Abs(q[0]) - 0.6) < 3e-3 && Math.Abs(Math.Abs(q[3]) - 0.8) < 3e-3;
                float[] sh = new float[2 * UgsPacking.ShFloat32Stride];
                for (int i = 0; i < sh.Length; i++) sh[i] = 1f;
                UgsPacking.MirrorXShFloat32(sh, 2);
                // sh1 (index 1) unchanged, sh3 and sh4 negated, sh15 negated, padding unchanged
                ok &= sh[0] == 1f && sh[6] == -1f && sh[9] == -1f && sh[42] == -1f && sh[45] == 1f && sh[48 + 6] == -1f;
                Check(ok, "GPU writer: server state -> GPU order through the permutation; SH mirror in the Float32 layout");
            });
            Run("facelog", delegate { FaceLogTests(python); });
            Run("coords", delegate
            {
                AvatarData a = new AvatarData(1, 3);
                a.Position[0] = 1; a.Position[1] = 2; a.Position[2] = 3;
                a.Rotation[0] = 0.1f; a.Rotation[1] = 0.2f; a.Rotation[2] = 0.3f; a.Rotation[3] = 0.9f;
                for (int i = 0; i < a.Sh.Length; i++) a.Sh[i] = 1;
                Coords.MirrorX(a);
                bool shOk = true;
                for (int k = 0; k < 16; k++)
                {
                    bool odd = Array.IndexOf(Coords.ShOddInX, k) >= 0;
                    for (int c = 0; c < 3; c++) if (a.Sh[3 * k + c] != (odd ? -1 : 1)) shOk = false;
                }
                Check(a.Position[0] == -1 && a.Position[1] == 2 && a.Rotation[0] == 0.1f && a.Rotation[1] == -0.2f && a.Rotation[2] == -0.3f && a.Rotation[3] == 0.9f && shOk,
                      "coords: mirror x of position, quaternion and SH (3, 4, 7, 10, 13, 15)");
            });
            Run("latency", delegate
            {
                LatencyStats s = new LatencyStats(100);
                for (int i = 1; i <= 100; i++) s.Add(i);
                Check(s.Count == 100 && s.Percentile(50) == 50 && s.Percentile(99) == 99 && s.Max == 100 && Math.Abs(s.Mean - 50.5) < 1e-9, "latency statistics (count, mean, percentiles)");
            });
            Run("layouts", delegate
            {
                Check(Layouts.Ovr63.Length == 63 && Layouts.Ovr70.Length == 70 && Layouts.Arkit52.Length == 52 && Layouts.Arkit51.Length == 51 &&
                      Layouts.Mediapipe52.Length == 52 && Layouts.Livelink61.Length == 61 && Layouts.Mediapipe52[1] == "browDownLeft" && Layouts.Livelink61[0] == "EyeBlinkLeft",
                      "layout name tables have the protocol's lengths");
            });
            Run("client options", delegate
            {
                Check(OferaClient.MakeUri("ws://h:1").AbsolutePath == "/v1/stream" && OferaClient.MakeUri("ws://h:1/x").AbsolutePath == "/x", "URL without a path gets /v1/stream");
                bool threw = false;
                try { new OferaClient(new OferaClientOptions { Layout = "ovr99" }); } catch (ArgumentException) { threw = true; }
                Check(threw, "unknown layout refused before connecting");
            });
        }

        static double Sq(double x) { return x * x; }

        static void MsgPackTests()
        {
            MsgPackWriter w = new MsgPackWriter(8);
            long[] ints = { 0, 1, 127, 128, 255, 256, 65535, 65536, 4294967295L, 4294967296L, long.MaxValue, -1, -32, -33, -128, -129, -32768, -32769, int.MinValue, (long)int.MinValue - 1, long.MinValue };
            w.WriteArrayHeader(ints.Length + 7);
            foreach (long i in ints) w.WriteInt(i);
            w.WriteUInt64(ulong.MaxValue);
            w.WriteFloat32(1.5f);
            w.WriteFloat64(-2.25);
            w.WriteBool(true);
            w.WriteNil();
            w.WriteString(new string('x', 300));
            w.WriteBin(new byte[70000], 0, 70000);
            MsgPackReader r = new MsgPackReader(w.Buffer, 0, w.Length);
            bool ok = r.ReadArrayHeader() == ints.Length + 7;
            foreach (long i in ints) ok &= r.ReadInt64() == i;
            bool of; r.ReadInteger(out of); ok &= of;
            ok &= r.ReadDouble() == 1.5 && r.ReadDouble() == -2.25 && r.ReadBool() && r.TryReadNil() && r.ReadString().Length == 300;
            int bo, bl; r.ReadBinSegment(out bo, out bl); ok &= bl == 70000 && r.Position == w.Length;
            Check(ok, "msgpack: ints of every width, uint64 overflow, float32/64, bool, nil, str8/16, bin32 round-trip");

            // structural refusals (malformed)
            string[][] bad =
            {
                new[] { "81a474797065c7010100", "ext type" },
                new[] { "81a474797065a2ff00", "invalid UTF-8" },
                new[] { "81a474797065c1", "0xc1" },
                new[] { "81a47479706581a1618181a16281a163c0", "depth 5" },
                new[] { "81a474797065a2", "string beyond the end" },
                new[] { "81c401617b", "bin key" },
                new[] { "", "empty" },
            };
            foreach (string[] b in bad)
            {
                byte[] bytes = Hex(b[0]);
                string got = "(accepted)";
                try { MsgPackReader.Validate(bytes, 0, bytes.Length); } catch (ProtocolException e) { got = e.Code; }
                Check(got == "malformed", "msgpack: refuses " + b[1], got);
            }
            MsgPackWriter big = new MsgPackWriter();
            big.WriteMapHeader(1); big.WriteString("type"); big.WriteArrayHeader(257);
            for (int i = 0; i < 257; i++) big.WriteInt(i);
            string g2 = "(accepted)";
            try { MsgPackReader.Validate(big.Buffer, 0, big.Length); } catch (ProtocolException e) { g2 = e.Code; }
            Check(g2 == "malformed", "msgpack: refuses a 257-entry array", g2);
            MsgPackWriter deep = new MsgPackWriter();
            deep.WriteMapHeader(1); deep.WriteString("a"); deep.WriteMapHeader(1); deep.WriteString("b"); deep.WriteMapHeader(1); deep.WriteString("c"); deep.WriteArrayHeader(0);
            bool accepted = true;
            try { MsgPackReader.Validate(deep.Buffer, 0, deep.Length); } catch (ProtocolException) { accepted = false; }
            Check(accepted, "msgpack: accepts nesting of exactly 4");
            string g3 = "(accepted)";
            byte[] huge = new byte[100];
            try { new ServerMessageDecoder().Decode(huge, 0, 100, null, new ServerMessage(), 50); } catch (ProtocolException e) { g3 = e.Code; }
            Check(g3 == "message_too_large", "decoder: message over the size limit is message_too_large", g3);
        }

        static void FaceLogTests(string python)
        {
            string[][] cases = { new[] { "0.0123", "0.0123" }, new[] { "1e-05", "1e-05" }, new[] { "0.333333333", "0.333333" }, new[] { "123456789", "1.23457e+08" },
                                 new[] { "0.5", "0.5" }, new[] { "1", "1" }, new[] { "0.0001", "0.0001" }, new[] { "-2.5e-7", "-2.5e-07" }, new[] { "1e+100", "1e+100" } };
            bool ok = true; string bad = "";
            foreach (string[] c in cases)
            {
                string got = FaceLogWriter.FormatG6(double.Parse(c[0], CultureInfo.InvariantCulture));
                if (got != c[1]) { ok = false; bad += c[0] + "->" + got + " "; }
            }
            Check(ok, "facelog: numbers formatted like Python's %.6g", bad);

            string path = Path.Combine(Path.GetTempPath(), "ofera_facelog_" + Process.GetCurrentProcess().Id + ".csv");
            float[] wts = new float[63];
            using (FaceLogWriter fl = FaceLogWriter.Create(path, "ovr63", "Quest Pro, Unity recorder (test)", true, true, "headset", "Quest Pro"))
            {
                for (int row = 0; row < 5; row++)
                {
                    for (int i = 0; i < 63; i++) wts[i] = (float)((i * 7 + row) % 64) / 64f;
                    fl.Write(1000.0 + row / 72.0, wts, 0.98f, 0.95f, row == 3 ? "audio" : "visual");
                }
            }
            string[] lines = File.ReadAllLines(path);
            Check(lines[0] == "# ofera facelog 1" && lines[1] == "# layout: ovr63" && lines[4].StartsWith("time,BROW_LOWERER_L,") &&
                  lines[4].EndsWith(",UPPER_LIP_RAISER_R,confidence_lower,confidence_upper,data_source") && lines.Length == 10 && lines[5].StartsWith("1000.000000,0,0.109375,"),
                  "facelog: header and rows as FACELOG.md specifies", lines.Length > 5 ? lines[5].Substring(0, Math.Min(60, lines[5].Length)) : "short file");
            if (python == null) { Console.WriteLine("SKIP facelog read back by ofera.sources.read_facelog (no --python)"); return; }
            string script = "import sys\nfrom ofera.sources import read_facelog\nlog = read_facelog(sys.argv[1])\n" +
                            "assert log.layout.name == 'ovr63', log.layout.name\nassert log.weights.shape == (5, 63), log.weights.shape\n" +
                            "assert abs(float(log.weights[1, 1]) - 8/64) < 1e-6, log.weights[1, 1]\nprint('ok', log.weights.shape)\n";
            RunPython(python, script, path, "facelog: file read back by ofera.sources.read_facelog");
            File.Delete(path);
            FaceLogTrackerTimeTests(python);
        }

        /// Writes `script` next to `path`, runs it with `python script path`, and checks that it exits 0 (the
        /// check is named `name`; its detail is the script's output). The script file is deleted afterwards.
        static void RunPython(string python, string script, string path, string name)
        {
            string scriptPath = path + ".py";
            File.WriteAllText(scriptPath, script);
            try
            {
                ProcessStartInfo psi = new ProcessStartInfo(python, "\"" + scriptPath + "\" \"" + path + "\"");
                psi.UseShellExecute = false; psi.RedirectStandardOutput = true; psi.RedirectStandardError = true;
                using (Process p = Process.Start(psi))
                {
                    Task<string> err = p.StandardError.ReadToEndAsync();  // both pipes drained: no deadlock on a full one
                    string output = p.StandardOutput.ReadToEnd() + err.Result;
                    p.WaitForExit();
                    Check(p.ExitCode == 0, name, output.Trim());
                }
            }
            finally { File.Delete(scriptPath); }
        }

        /// The recorder's Quest format: a Face_Time column (tracker clock); rows repeating a tracker time are
        /// one sample to the reader, which times samples by Face_Time.
        static void FaceLogTrackerTimeTests(string python)
        {
            string path = Path.Combine(Path.GetTempPath(), "ofera_facelog_tracker_" + Process.GetCurrentProcess().Id + ".csv");
            float[] wts = new float[70];
            bool refused = false;
            using (FaceLogWriter fl = FaceLogWriter.Create(path, "ovr70", "Quest Pro, Unity recorder (test)", true, false))
            {
                fl.TrackerTime = true;
                try { fl.Write(0.0, wts); } catch (InvalidOperationException) { refused = true; }
                Check(refused, "facelog: a Face_Time log refuses a row without tracker time");
                double[] tracker = { 8000.0, 8000.0 + 1 / 36.0, 8000.0 + 1 / 36.0, 8000.0 + 2 / 36.0, 8000.0 + 3 / 36.0, 8000.0 + 3 / 36.0 };
                for (int row = 0; row < tracker.Length; row++)
                {
                    for (int i = 0; i < 70; i++) wts[i] = (float)((i + 3 * (int)Math.Round((tracker[row] - 8000.0) * 36)) % 64) / 64f;
                    fl.Write(row / 83.0, tracker[row], wts, 0.9f, 0.3f);
                }
                bool late = false;
                try { fl.TrackerTime = false; } catch (InvalidOperationException) { late = true; }
                Check(late, "facelog: TrackerTime cannot change after the header");
            }
            string[] lines = File.ReadAllLines(path);
            Check(lines[3].StartsWith("time,Face_Time,BROW_LOWERER_L,") && lines[3].EndsWith(",TONGUE_RETREAT,confidence_lower,confidence_upper")
                  && lines[4].StartsWith("0.000000,8000.000000,0,"),
                  "facelog: Face_Time column after time", lines.Length > 4 ? lines[3].Substring(0, 40) + " / " + lines[4].Substring(0, 30) : "short file");
            if (python == null) { Console.WriteLine("SKIP facelog with Face_Time read back (no --python)"); File.Delete(path); return; }
            string script = "import sys\nimport numpy as np\nfrom ofera.sources import read_facelog\nlog = read_facelog(sys.argv[1])\n" +
                            "assert log.layout.name == 'ovr70', log.layout.name\nassert log.weights.shape == (4, 70), log.weights.shape\n" +
                            "assert np.allclose(log.times, np.arange(4) / 36.0, atol=2e-6), log.times\n" +
                            "assert np.allclose(log.confidence, [[0.9, 0.3]] * 4), log.confidence\nprint('ok', log.weights.shape)\n";
            RunPython(python, script, path, "facelog: Face_Time log read back as one sample per tracker time");
            File.Delete(path);
        }

        // ============================================================ live server

        static float[] Sample(int layoutLength, int k)
        {
            float[] w = new float[layoutLength];
            double ph = k * 0.15;
            w[24 % layoutLength] = (float)(0.5 + 0.5 * Math.Sin(ph));           // JAW_DROP in ovr63
            w[32 % layoutLength] = (float)(0.5 + 0.5 * Math.Sin(ph * 0.7));     // LIP_CORNER_PULLER_L
            w[33 % layoutLength] = (float)(0.5 + 0.5 * Math.Sin(ph * 0.7 + 1)); // LIP_CORNER_PULLER_R
            w[12 % layoutLength] = k % 20 < 2 ? 1f : 0f;                         // blink
            return w;
        }

        static void Drain(OferaClient c, List<ClientEvent> into)
        {
            ClientEvent e;
            while (c.TryDequeueEvent(out e)) { into.Add(e); Console.WriteLine("  event " + e); }
        }

        static bool WaitFor(Func<bool> cond, double seconds, OferaClient c, List<ClientEvent> events)
        {
            Stopwatch sw = Stopwatch.StartNew();
            while (sw.Elapsed.TotalSeconds < seconds)
            {
                if (c != null) Drain(c, events);
                if (cond()) return true;
                Thread.Sleep(2);
            }
            if (c != null) Drain(c, events);
            return cond();
        }

        static void LiveTests(string url, int frames)
        {
            Run("live client session", delegate { LiveClientSession(url, frames); });
            Run("live low-level sessions", delegate { LowLevelSessions(url); });
            Run("live GPU-path session", delegate { LivePayloadSession(url); });
            Run("live delta session", delegate { DeltaTests.Live(url, Check, Sample, WaitFor); }); // PROTOCOL.md 7.1
        }

        /// <summary>The GPU upload path against the real server: payload kept, no float decode on the receive thread.</summary>
        static void LivePayloadSession(string url)
        {
            OferaClientOptions o = new OferaClientOptions();
            o.Url = url; o.Layout = "ovr63"; o.Encoding = "q13"; o.Sparse = true; o.Coords = "unity";
            o.KeepPayload = true; o.DecodeValues = false; o.HandshakeTimeoutSeconds = 120; o.PingIntervalSeconds = 0;
            List<ClientEvent> events = new List<ClientEvent>();
            OferaClient c = new OferaClient(o);
            c.Start();
            AvatarData avatar = null; Welcome welcome = null; int session = 0;
            bool got = WaitFor(() => c.TryTakeAvatar(out avatar, out welcome, out session), 180, c, events);
            Check(got, "live gpu: handshake and avatar", "status " + c.Status);
            if (!got) { c.Stop(); return; }
            int frames = 0;
            string problems = "";
            float[] pos = new float[3 * avatar.Count];
            for (int k = 0; k < 10; k++)
            {
                c.SubmitBlendshapes(Sample(63, k), OferaClock.NowMicros());
                FrameData f = null;
                int want = k;
                if (!WaitFor(() => { FrameData x = c.TryTakeFrame(); if (x != null && x.Seq >= want) { f = x; return true; } return false; }, 30, c, events)) break;
                frames++;
                FramePayload p = f.Payload;
                if (f.HasValues) problems += " values decoded;";
                if (p.N != f.N || p.Encoding != FrameEncoding.Q13 || p.HasIndex != f.HasIndex) problems += " header;";
                if (p.Words != (p.HasIndex ? p.N : 0) + (6 * p.N + 3) / 4 + p.N + (3 * p.N + 3) / 4) problems += " size " + p.Words + ";";
                for (int i = 0; i < p.N && p.HasIndex; i++)
                    if (BitCast.ReadUInt32LE(p.Bytes, 4 * (p.IndexWord + i)) != f.Index[i]) { problems += " index;"; break; }
                FrameCodec.DecodeQ13Positions(p.Bytes, 4 * p.PositionWord, p.N, welcome.Quant, pos, 0);
                for (int i = 0; i < 3 * p.N; i++)
                {
                    int a = i % 3;
                    if (!(pos[i] >= welcome.Quant.PosMin[a] - 1e-6f && pos[i] <= welcome.Quant.PosMax[a] + 1e-6f)) { problems += " position outside the box;"; break; }
                }
            }
            c.Stop();
            Check(frames == 10 && problems.Length == 0, "live gpu: 10 frames with their wire payload kept (no float decode), index and q13 positions read back",
                  frames + " frames;" + problems);
        }

        static void LiveClientSession(string url, int frames)
        {
            OferaClientOptions o = new OferaClientOptions();
            o.Url = url; o.Layout = "ovr63"; o.Encoding = "q13"; o.Sparse = true; o.Coords = "unity";
            o.InitialBackoffSeconds = 0.2; o.HandshakeTimeoutSeconds = 120; o.PingIntervalSeconds = 0.5;
            List<ClientEvent> events = new List<ClientEvent>();
            OferaClient c = new OferaClient(o);
            c.Start();
            AvatarData avatar = null; Welcome welcome = null; int session = 0;
            bool got = WaitFor(() => c.TryTakeAvatar(out avatar, out welcome, out session), 180, c, events);
            Check(got && avatar != null && avatar.Count > 0 && welcome.Encoding == "q13" && welcome.Coords == "unity",
                  "live: handshake (hello ovr63/q13/unity/sparse -> welcome) and avatar received",
                  got ? avatar.Count + " Gaussians" : "status " + c.Status);
            if (!got) { c.Stop(); return; }
            Console.WriteLine("  welcome: session " + welcome.Session + ", " + welcome.Count + " Gaussians, sh " + welcome.ShDegree + ", sparse " + welcome.Sparse + ", server " + welcome.Server);
            GaussianState state = new GaussianState(avatar);
            int received = 0, applied = 0, sparseFrames = 0;
            bool finite = true;
            long lastSeq = -1;
            Stopwatch sw = Stopwatch.StartNew();
            for (int k = 0; k < frames; k++)
            {
                c.SubmitBlendshapes(Sample(63, k), OferaClock.NowMicros());
                FrameData f = null;
                int want = k;
                bool ok = WaitFor(() => { FrameData x = c.TryTakeFrame(); if (x != null && x.Seq >= want) { f = x; return true; } return false; }, 30, c, events);
                if (!ok) { Console.WriteLine("  no frame for bs " + k + " (status " + c.Status + ")"); break; }
                received++;
                if (f.Seq > lastSeq && f.SessionNumber == session && state.Apply(f)) applied++;
                lastSeq = f.Seq;
                if (f.HasIndex) sparseFrames++;
                for (int i = 0; i < 3 * f.N && finite; i++) finite = BitCast.IsFinite(f.Position[i]);
            }
            double secs = sw.Elapsed.TotalSeconds;
            Check(received == frames && applied == frames, "live: " + frames + " frames received and applied (lockstep bs -> frame)",
                  received + " received, " + applied + " applied");
            Check(finite, "live: frame positions finite");
            Console.WriteLine("  " + received + " frames in " + secs.ToString("F2") + " s; sparse frames " + sparseFrames + "; round trip " + c.Stats.RoundTrip.Summary() +
                              "; server total " + c.Stats.ServerTotal.Summary() + "; ping " + c.Stats.PingRoundTrip.Summary());
            Check(c.Stats.RoundTrip.Count >= frames && c.Stats.RoundTrip.Percentile(50) > 0, "live: latency statistics from echoed t", c.Stats.RoundTrip.Summary());

            // injected bad bs: NaN weight -> non-fatal error, the session goes on
            float[] bad = Sample(63, 0);
            bad[5] = float.NaN;
            MsgPackWriter w = new MsgPackWriter();
            ClientMessageEncoder.Bs(w, 100000, OferaClock.NowMicros(), bad, 63);
            int eventsBefore = events.Count;
            c.SendRawForTesting(w.ToArray());
            ClientEvent errEvent = null;
            WaitFor(() =>
            {
                for (int i = eventsBefore; i < events.Count; i++) if (events[i].Kind == ClientEventKind.ServerError) { errEvent = events[i]; return true; }
                return false;
            }, 20, c, events);
            Check(errEvent != null && !errEvent.Error.Fatal && errEvent.Error.Code == "non_finite",
                  "live: injected bad bs answered with a non-fatal error", errEvent == null ? "no error event" : errEvent.Error.ToString());
            long before = c.Stats.FramesReceived;
            c.SubmitBlendshapes(Sample(63, 1), OferaClock.NowMicros());
            bool goesOn = WaitFor(() => c.Stats.FramesReceived > before && c.Status == ClientStatus.Streaming, 30, c, events);
            Check(goesOn, "live: session goes on after the error", "status " + c.Status);

            // reconnect: drop the socket as a network failure would
            c.AbortConnectionForTesting();
            AvatarData a2 = null; Welcome w2 = null; int s2 = 0;
            bool again = WaitFor(() => c.TryTakeAvatar(out a2, out w2, out s2), 180, c, events);
            Check(again && s2 == session + 1 && a2.Count == avatar.Count && c.Stats.Reconnects >= 1,
                  "live: reconnect after a dropped connection (backoff, fresh handshake, avatar again)", again ? "session " + s2 : "status " + c.Status);
            if (again)
            {
                c.SubmitBlendshapes(Sample(63, 2), OferaClock.NowMicros());
                FrameData f2 = null;
                bool fr = WaitFor(() => { FrameData x = c.TryTakeFrame(); if (x != null) f2 = x; return f2 != null; }, 30, c, events);
                Check(fr && f2.SessionNumber == s2 && f2.Seq == 0, "live: frames flow in the new session (seq restarts at 0)", fr ? "seq " + f2.Seq + " session " + f2.SessionNumber : "none");
            }
            c.Stop(2000);
            Drain(c, events);
            Check(c.Status == ClientStatus.Stopped, "live: stop sends bye and closes", c.Status.ToString());
            Console.WriteLine("  stats: frames " + c.Stats.FramesReceived + ", dropped before take " + c.Stats.FramesDropped + ", skipped by server " + c.Stats.FramesSkippedByServer +
                              ", bs sent " + c.Stats.BsSent + ", bytes " + c.Stats.BytesReceived + ", sessions " + c.Stats.Sessions);
        }

        // raw ClientWebSocket + ClientConnection, for what the high-level client does not expose
        internal sealed class Raw : IDisposable
        {
            public readonly ClientWebSocket Ws = new ClientWebSocket();
            public readonly ClientConnection Conn = new ClientConnection();
            public readonly ServerMessage Msg = new ServerMessage();
            public readonly byte[] Rx = new byte[Protocol.MaxServerMessage];
            public readonly MsgPackWriter W = new MsgPackWriter();

            public void Connect(string url)
            {
                Ws.ConnectAsync(new Uri(url), CancellationToken.None).Wait(20000);
            }

            public void Send(MsgPackWriter w)
            {
                Ws.SendAsync(w.Segment, WebSocketMessageType.Binary, true, CancellationToken.None).Wait(20000);
            }

            /// <summary>Next message: its length, -1 on close. Throws on timeout.</summary>
            public int Next(double seconds = 60)
            {
                int filled = 0;
                while (true)
                {
                    Task<WebSocketReceiveResult> t = Ws.ReceiveAsync(new ArraySegment<byte>(Rx, filled, Rx.Length - filled), CancellationToken.None);
                    if (!t.Wait(TimeSpan.FromSeconds(seconds))) throw new TimeoutException("no message in " + seconds + " s");
                    WebSocketReceiveResult r = t.Result;
                    if (r.MessageType == WebSocketMessageType.Close) return -1;
                    filled += r.Count;
                    if (r.EndOfMessage) return filled;
                }
            }

            public ServerMessageKind Receive(double seconds = 60)
            {
                int n = Next(seconds);
                if (n < 0) return ServerMessageKind.None;
                if (Msg.Frame == null) Msg.Frame = new FrameData();
                return Conn.Receive(Rx, 0, n, Msg);
            }

            public void Dispose() { try { Ws.Abort(); } catch (Exception) { } Ws.Dispose(); }
        }

        static void LowLevelSessions(string url)
        {
            // a bad handshake: fatal error, then the server closes with the error's close code
            using (Raw r = new Raw())
            {
                r.Connect(url);
                r.W.Clear();
                r.W.WriteMapHeader(3); r.W.WriteString("type"); r.W.WriteString("hello"); r.W.WriteString("protocol"); r.W.WriteInt(1);
                r.W.WriteString("layout"); r.W.WriteString("ovr99");
                r.Send(r.W);
                ServerMessage m = new ServerMessage();
                int n = r.Next(30);
                string got = "(closed)";
                if (n > 0)
                {
                    ServerMessageDecoder d = new ServerMessageDecoder();
                    byte[] copy = new byte[n];
                    // decode outside a connection (the state machine would throw as it closes)
                    Array.Copy(r.Rx, copy, n);
                    d.Decode(copy, 0, n, null, m);
                    got = m.Kind == ServerMessageKind.Error ? m.Error.Code + (m.Error.Fatal ? " fatal" : "") : m.Kind.ToString();
                }
                int closed = r.Next(30);
                Check(got == "unknown_layout fatal" && closed == -1 && r.Ws.CloseStatus.HasValue && (int)r.Ws.CloseStatus.Value == 4011,
                      "live: bad hello -> fatal unknown_layout and close 4011", got + ", close " + (r.Ws.CloseStatus.HasValue ? ((int)r.Ws.CloseStatus.Value).ToString() : "none"));
            }

            foreach (string enc in new[] { "f32", "f16" })
            {
                bool sparse = enc == "f16";
                using (Raw r = new Raw())
                {
                    r.Connect(url);
                    Hello h = new Hello(); h.Layout = "arkit52"; h.Encoding = enc; h.Coords = "unity"; h.Sparse = sparse;
                    r.Conn.EncodeHello(h, r.W);
                    r.Send(r.W);
                    while (r.Conn.State != ClientState.Streaming)
                    {
                        ServerMessageKind k = r.Receive(180);
                        if (k == ServerMessageKind.None) throw new Exception("closed during the handshake");
                    }
                    GaussianState st = new GaussianState(r.Conn.Avatar);
                    float[] w = new float[52];
                    w[17] = 0.8f; // jawOpen
                    r.Conn.EncodeBs(0, OferaClock.NowMicros(), w, r.W);
                    r.Send(r.W);
                    ServerMessageKind kind = NextNonPong(r);
                    bool frameOk = kind == ServerMessageKind.Frame && r.Msg.Frame.Seq == 0 && r.Msg.Frame.HasIndex == (sparse && r.Conn.Welcome.Sparse) && st.Apply(r.Msg.Frame);
                    Check(frameOk, "live " + enc + (sparse ? " sparse" : " dense") + ": frame decoded and applied", kind + " n=" + r.Msg.Frame.N);
                    // bs of the wrong length -> non-fatal bad_length with its seq
                    r.W.Clear();
                    ClientMessageEncoder.Bs(r.W, 1, OferaClock.NowMicros(), w, 51);
                    r.Send(r.W);
                    kind = NextNonPong(r);
                    // `seq` is optional in an error ("when known"); if present it must be the offending bs's
                    Check(kind == ServerMessageKind.Error && r.Msg.Error.Code == "bad_length" && !r.Msg.Error.Fatal && (!r.Msg.Error.Seq.HasValue || r.Msg.Error.Seq == 1),
                          "live " + enc + ": bs of the wrong length -> non-fatal bad_length", kind == ServerMessageKind.Error ? r.Msg.Error.ToString() : kind.ToString());
                    if (kind == ServerMessageKind.Error && !r.Msg.Error.Seq.HasValue) Console.WriteLine("  note: the server's error carries no seq");
                    r.Conn.EncodeBs(2, OferaClock.NowMicros(), w, r.W);
                    r.Send(r.W);
                    kind = NextNonPong(r);
                    Check(kind == ServerMessageKind.Frame && r.Msg.Frame.Seq == 2, "live " + enc + ": next bs still answered", kind.ToString());
                    r.Conn.EncodePing(12345, r.W);
                    r.Send(r.W);
                    kind = r.Receive(30);
                    Check(kind == ServerMessageKind.Pong && r.Msg.PongT == 12345, "live " + enc + ": ping -> pong with the same t", kind.ToString());
                    r.Conn.EncodeBye(r.W);
                    r.Send(r.W);
                    int closed = r.Next(30);
                    Check(closed == -1 && r.Ws.CloseStatus.HasValue && r.Ws.CloseStatus.Value == WebSocketCloseStatus.NormalClosure, "live " + enc + ": bye -> close 1000");
                }
            }
        }

        static ServerMessageKind NextNonPong(Raw r)
        {
            while (true)
            {
                ServerMessageKind k = r.Receive(60);
                if (k != ServerMessageKind.Pong) return k;
            }
        }
    }
}
