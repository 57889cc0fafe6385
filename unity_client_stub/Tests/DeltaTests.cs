// Delta-session vectors (PROTOCOL.md 7.1) for the mono test program: hello_delta and resync re-encode byte for
// byte, welcome_delta announces the delta session, the key -> delta -> delta-after-a-drop sequences decode to
// every Gaussian's state in the JSON, and the invalid delta frames fail with their codes without touching the
// held codes. Called from TestMain.OneVector. C# 7.2.
using System;
using System.Collections.Generic;
using System.IO;
using System.Text;
using Ofera.Client;

namespace Ofera.Client.Tests
{
    static class DeltaTests
    {
        public delegate void CheckFn(bool ok, string name, string detail);

        static bool IsDeltaFormat(Dictionary<string, object> v, string key)
        {
            if (!J.Has(v, key)) return false;
            Dictionary<string, object> o = J.O(v[key]);
            if (key == "context") { if (!J.Has(o, "format")) return false; o = J.O(o["format"]); }
            return J.Has(o, "delta") && (bool)o["delta"];
        }

        /// <summary>True if this vector is a delta-session one (handled here, not by TestMain's generic checks).</summary>
        public static bool Handles(string name, Dictionary<string, object> v)
        {
            return name == "hello_delta" || name == "resync" || name == "welcome_delta" || IsDeltaFormat(v, "format")
                || IsDeltaFormat(v, "context");
        }

        static FrameFormat Format(Dictionary<string, object> f)
        {
            FrameFormat fmt = Program.FormatFromJson(f); // a delta session is dense
            fmt.Delta = new DeltaState(fmt.Encoding, fmt.Count, fmt.Quant);
            return fmt;
        }

        static byte[] Bytes(string dir, string name) { return File.ReadAllBytes(Path.Combine(dir, name + ".msgpack")); }

        static string Hex(MsgPackWriter w)
        {
            StringBuilder s = new StringBuilder();
            for (int i = 0; i < w.Length; i++) s.Append(w.Buffer[i].ToString("x2"));
            return s.ToString();
        }

        static string Compare(float[] got, double[] want, double rel)
        {
            for (int i = 0; i < want.Length; i++)
                if (!(Math.Abs(got[i] - want[i]) <= rel * Math.Abs(want[i]) + 1e-12))
                    return "element " + i + ": got " + got[i].ToString("R") + ", want " + want[i].ToString("R");
            return null;
        }

        public delegate bool WaitFn(Func<bool> cond, double seconds, OferaClient c, List<ClientEvent> events);

        /// <summary>Live: a q13 delta client and a plain q13 client get the same samples from `ofera serve`; the delta
        /// client's reconstruction (key frame + deltas, as OferaClient hands them over) stays within the server's
        /// tolerance (0.045 mm, so 5e-5 m per axis with q13's own error) of the plain one, frame after frame.</summary>
        public static void Live(string url, CheckFn check, Func<int, int, float[]> sample, WaitFn waitFor)
        {
            OferaClient[] cs = new OferaClient[2];
            float[][] state = new float[2][];
            List<ClientEvent> events = new List<ClientEvent>();
            for (int c = 0; c < 2; c++)
            {
                OferaClientOptions o = new OferaClientOptions();
                o.Url = url; o.Layout = "ovr63"; o.Encoding = "q13"; o.Sparse = false; o.Coords = "unity";
                o.Delta = c == 0; o.HandshakeTimeoutSeconds = 120; o.PingIntervalSeconds = 0;
                cs[c] = new OferaClient(o);
                cs[c].Start();
            }
            string problems = "";
            int keys = 0, deltas = 0;
            try
            {
                for (int c = 0; c < 2; c++)
                {
                    AvatarData avatar = null; Welcome welcome = null; int session = 0;
                    OferaClient cl = cs[c];
                    if (!waitFor(() => cl.TryTakeAvatar(out avatar, out welcome, out session), 180, cl, events))
                    { check(false, "live delta: handshake", "status " + cl.Status); return; }
                    if (welcome.Delta != (c == 0)) problems += " welcome.delta " + welcome.Delta + ";";
                    state[c] = new float[3 * avatar.Count];
                }
                double worst = 0;
                for (int k = 0; k < 12; k++)
                {
                    float[] w = sample(63, k);
                    for (int c = 0; c < 2; c++)
                    {
                        OferaClient cl = cs[c];
                        cl.SubmitBlendshapes(w, OferaClock.NowMicros());
                        FrameData f = null;
                        int want = k;
                        if (!waitFor(() => { FrameData x = cl.TryTakeFrame(); if (x != null && x.Seq >= want) { f = x; return true; } return false; }, 30, cl, events))
                        { problems += " no frame " + k + ";"; break; }
                        if (c == 0) { if (f.IsKey) keys++; else deltas++; }
                        for (int j = 0; j < f.N; j++)
                        {
                            int i = f.HasIndex ? (int)f.Index[j] : j;
                            Array.Copy(f.Position, 3 * j, state[c], 3 * i, 3);
                        }
                    }
                    for (int i = 0; i < state[0].Length; i++) worst = Math.Max(worst, Math.Abs(state[0][i] - state[1][i]));
                }
                check(problems.Length == 0 && keys >= 1 && deltas >= 1 && worst <= 5e-5,
                      "live delta: a q13 delta client stays within the tolerance of a q13 client",
                      problems + " keys " + keys + ", deltas " + deltas + ", worst " + worst.ToString("R") + " m");
            }
            finally
            {
                cs[0].Stop();
                cs[1].Stop();
            }
        }

        public static void Vector(string dir, string name, Dictionary<string, object> v, CheckFn check)
        {
            Dictionary<string, object> f = J.Has(v, "fields") ? J.O(v["fields"]) : null;
            byte[] bytes = Bytes(dir, name);
            if (name == "hello_delta" || name == "resync")
            {
                ClientMessage m = new ClientMessage();
                ClientMessageKind kind = new ClientMessageDecoder().Decode(bytes, 0, bytes.Length, null, m);
                MsgPackWriter w = new MsgPackWriter(64);
                bool ok;
                if (name == "resync") { ok = kind == ClientMessageKind.Resync; ClientMessageEncoder.Resync(w); }
                else
                {
                    ok = kind == ClientMessageKind.Hello && m.Hello.Delta == true && m.Hello.Encoding == "q13";
                    Hello h = new Hello();
                    h.Layout = (string)f["layout"];
                    h.Avatar = J.Has(f, "avatar") ? (string)f["avatar"] : null;
                    h.Encoding = (string)f["encoding"];
                    h.Coords = J.Has(f, "coords") ? (string)f["coords"] : null;
                    h.Sparse = J.Has(f, "sparse") ? (bool?)(bool)f["sparse"] : null;
                    h.Delta = true;
                    ClientMessageEncoder.Hello(w, h);
                }
                check(ok, "vector " + name + " decodes to its JSON", kind.ToString());
                check(Hex(w) == (string)v["hex"], "vector " + name + " re-encodes byte-identical", Hex(w));
                return;
            }
            if (name == "welcome_delta")
            {
                ServerMessage m = new ServerMessage();
                new ServerMessageDecoder().Decode(bytes, 0, bytes.Length, null, m);
                FrameFormat fmt = m.Welcome.ToFormat();
                check(m.Welcome.Delta && fmt.Delta != null && fmt.Delta.Encoding == FrameEncoding.Q13 && !fmt.Sparse,
                      "vector " + name + " announces a q13 delta session", null);
                return;
            }
            if (J.Has(v, "expect_error"))
            {
                FrameFormat fmt = Format(J.O(J.O(v["context"])["format"]));
                fmt.Delta.HasKey = true;
                string want = (string)J.O(v["expect_error"])["code"], got = "(no error)";
                try { new ServerMessageDecoder().Decode(bytes, 0, bytes.Length, fmt, new ServerMessage()); }
                catch (ProtocolException e) { got = e.Code; }
                bool untouched = Array.TrueForAll(fmt.Delta.PositionCodes, x => x == 0);
                check(got == want && untouched && fmt.Delta.ResyncNeeded, "vector " + name + " -> error " + want + ", state kept",
                      "got " + got);
                return;
            }
            // a key / delta sequence: apply `after`, then this frame; compare every Gaussian's state
            FrameFormat sf = Format(J.O(v["format"]));
            int count = sf.Count;
            float[] pos = new float[3 * count], rot = new float[4 * count], scl = new float[3 * count];
            List<string> steps = new List<string>();
            if (J.Has(v, "after")) foreach (object o in (List<object>)v["after"]) steps.Add((string)o);
            steps.Add(name);
            ServerMessageDecoder dec = new ServerMessageDecoder();
            ServerMessage sm = new ServerMessage();
            string problems = "";
            foreach (string step in steps)
            {
                byte[] b = Bytes(dir, step);
                dec.Decode(b, 0, b.Length, sf, sm);
                FrameData fr = sm.Frame;
                bool wantKey = step.EndsWith("_key");
                if (fr.IsKey != wantKey || fr.HasIndex == wantKey) problems += " " + step + ": key/index";
                for (int j = 0; j < fr.N; j++)
                {
                    int i = fr.HasIndex ? (int)fr.Index[j] : j;
                    Array.Copy(fr.Position, 3 * j, pos, 3 * i, 3);
                    Array.Copy(fr.Rotation, 4 * j, rot, 4 * i, 4);
                    Array.Copy(fr.Scale, 3 * j, scl, 3 * i, 3);
                }
            }
            if (sm.Frame.Seq != J.I(f["seq"]) || sm.Frame.N != J.I(f["n"])) problems += " seq/n";
            Dictionary<string, object> dj = J.O(v["decoded"]);
            string c = Compare(pos, J.Flat(dj["position"]), 0) ?? Compare(rot, J.Flat(dj["rotation"]), 0)
                       ?? Compare(scl, J.Flat(dj["scale"]), 1e-6);
            if (c != null) problems += " " + c;
            check(problems.Length == 0, "vector " + name + " (after " + (steps.Count - 1) + " frames) decodes to its JSON", problems);
        }
    }
}
