// Rooms (PROTOCOL.md 12) for the mono test program: the room golden vectors (hellos byte for byte, welcome, join,
// leave), a room session on hand-built messages (joins, member avatars, routed frames, leaves, watch-only members,
// the frame pool), and live: OferaClients in a room of `ofera serve` where a Python client publishes (its join,
// avatar and frames arrive with its member id; its leave when it goes), a C# publisher sees itself (`self`) and a
// C# watcher sees the C# publisher. Called from TestMain. C# 7.2.
using System;
using System.Collections.Generic;
using System.Diagnostics;
using System.IO;
using System.Text;
using Ofera.Client;

namespace Ofera.Client.Tests
{
    static class RoomTests
    {
        public delegate void CheckFn(bool ok, string name, string detail = null);
        public delegate void RunFn(string name, Action body);
        public delegate bool WaitFn(Func<bool> cond, double seconds, OferaClient c, List<ClientEvent> events);

        static readonly string[] VectorNames =
            { "hello_room", "hello_room_watch", "welcome_room", "welcome_room_watch", "join", "join_f16", "join_watch", "leave" };

        /// <summary>True for the room vectors handled here (the member avatar and frames go through TestMain's generic checks).</summary>
        public static bool Handles(string name) { return Array.IndexOf(VectorNames, name) >= 0; }

        static string Hex(byte[] b, int off, int len)
        {
            StringBuilder s = new StringBuilder();
            for (int i = off; i < off + len; i++) s.Append(b[i].ToString("x2"));
            return s.ToString();
        }

        static string Str(Dictionary<string, object> f, string k) { return J.Has(f, k) ? (string)f[k] : null; }

        public static void Vector(string dir, string name, Dictionary<string, object> v, CheckFn check)
        {
            byte[] bytes = File.ReadAllBytes(Path.Combine(dir, name + ".msgpack"));
            Dictionary<string, object> f = J.O(v["fields"]);
            string problems = "";
            if ((string)v["direction"] == "client_to_server")
            {
                ClientMessage m = new ClientMessage();
                new ClientMessageDecoder().Decode(bytes, 0, bytes.Length, null, m);
                Hello h = m.Hello;
                bool publish = !J.Has(f, "publish") || (bool)f["publish"];
                bool self = J.Has(f, "self") && (bool)f["self"];
                if (h.Room != (string)f["room"] || h.Publish != publish || h.Self != self || h.RoomToken != Str(f, "room_token"))
                    problems += " room/publish/self/room_token";
                Hello e = new Hello();
                e.Layout = (string)f["layout"]; e.Avatar = Str(f, "avatar"); e.Encoding = Str(f, "encoding"); e.Coords = Str(f, "coords");
                e.Sparse = J.Has(f, "sparse") ? (bool?)(bool)f["sparse"] : null;
                e.Room = (string)f["room"]; e.Publish = publish; e.Self = self; e.RoomToken = Str(f, "room_token");
                MsgPackWriter w = new MsgPackWriter(256);
                ClientMessageEncoder.Hello(w, e);
                check(Hex(w.Buffer, 0, w.Length) == Hex(bytes, 0, bytes.Length), "vector " + name + " re-encodes byte-identical", Hex(w.Buffer, 0, w.Length));
                check(problems.Length == 0, "vector " + name + " decodes to its JSON", problems);
                return;
            }
            ServerMessage s = new ServerMessage();
            ServerMessageKind kind = new ServerMessageDecoder().Decode(bytes, 0, bytes.Length, null, s);
            switch ((string)f["type"])
            {
                case "welcome":
                    {
                        Welcome wm = s.Welcome;
                        if (kind != ServerMessageKind.Welcome || wm.Room != (string)f["room"] || wm.Member != (string)f["member"]) problems += " room/member";
                        if (J.Has(f, "avatar") ? wm.AvatarId != (string)J.O(f["avatar"])["id"] || wm.Count != J.I(J.O(f["avatar"])["count"]) : wm.AvatarId != null)
                            problems += " avatar";
                        if (wm.Quant != null) problems += " quant (a room welcome has none)";
                        break;
                    }
                case "join":
                    {
                        JoinMessage j = s.Join;
                        bool publish = !J.Has(f, "publish") || (bool)f["publish"];
                        if (kind != ServerMessageKind.Join || j.Member != (string)f["member"] || j.Publish != publish) problems += " member/publish";
                        if (J.Has(f, "avatar"))
                        {
                            Dictionary<string, object> av = J.O(f["avatar"]);
                            if (j.AvatarId != (string)av["id"] || j.Count != J.I(av["count"]) || j.ShDegree != J.I(av["sh_degree"])) problems += " avatar";
                        }
                        else if (j.AvatarId != null) problems += " unexpected avatar";
                        if (J.Has(f, "quant") != (j.Quant != null)) problems += " quant";
                        else if (j.Quant != null && Math.Abs(j.Quant.PosMin[0] - J.Values(J.O(J.O(f["quant"])["pos_min"]))[0]) > 1e-9) problems += " quant values";
                        break;
                    }
                case "leave":
                    if (kind != ServerMessageKind.Leave || s.Leave.Member != (string)f["member"] || s.Leave.Reason != (string)f["reason"]) problems += " member/reason";
                    break;
            }
            check(problems.Length == 0, "vector " + name + " decodes to its JSON", problems);
        }

        // ============================================================ a room session on hand-built messages

        static byte[] Msg(MsgPackWriter w) { byte[] b = new byte[w.Length]; Buffer.BlockCopy(w.Buffer, 0, b, 0, w.Length); return b; }

        /// <summary>welcome of a room session (PROTOCOL.md 12.2): an own avatar only when publishing, no quant.</summary>
        static byte[] RoomWelcome(string room, string member, bool publish = true)
        {
            MsgPackWriter w = new MsgPackWriter();
            w.WriteMapHeader(7 + (publish ? 1 : 0) + (room != null ? 2 : 0));
            w.WriteString("type"); w.WriteString("welcome");
            w.WriteString("protocol"); w.WriteInt(1);
            w.WriteString("session"); w.WriteString("room-test");
            if (publish)
            {
                w.WriteString("avatar"); w.WriteMapHeader(3);
                w.WriteString("id"); w.WriteString("own"); w.WriteString("count"); w.WriteInt(2); w.WriteString("sh_degree"); w.WriteInt(0);
            }
            w.WriteString("layout"); w.WriteString("ovr63");
            w.WriteString("encoding"); w.WriteString("f32");
            w.WriteString("coords"); w.WriteString("unity");
            w.WriteString("sparse"); w.WriteBool(true);
            if (room != null) { w.WriteString("room"); w.WriteString(room); w.WriteString("member"); w.WriteString(member); }
            return Msg(w);
        }

        /// <summary>join of a publishing member (count Gaussians), or of a watch-only one (count &lt; 0).</summary>
        static byte[] Join(string member, int count)
        {
            MsgPackWriter w = new MsgPackWriter();
            w.WriteMapHeader(3);
            w.WriteString("type"); w.WriteString("join");
            w.WriteString("member"); w.WriteString(member);
            if (count < 0) { w.WriteString("publish"); w.WriteBool(false); return Msg(w); }
            w.WriteString("avatar"); w.WriteMapHeader(3);
            w.WriteString("id"); w.WriteString("default"); w.WriteString("count"); w.WriteInt(count); w.WriteString("sh_degree"); w.WriteInt(0);
            return Msg(w);
        }

        static byte[] Leave(string member, string reason)
        {
            MsgPackWriter w = new MsgPackWriter();
            w.WriteMapHeader(3);
            w.WriteString("type"); w.WriteString("leave");
            w.WriteString("member"); w.WriteString(member);
            w.WriteString("reason"); w.WriteString(reason);
            return Msg(w);
        }

        /// <summary>Avatar chunk of Gaussians [offset, offset + n) of count; position x = base + index.</summary>
        static byte[] Chunk(string member, int count, int chunk, int chunks, int offset, int n, float baseX)
        {
            MsgPackWriter w = new MsgPackWriter();
            w.WriteMapHeader(member != null ? 13 : 12);
            w.WriteString("type"); w.WriteString("avatar");
            if (member != null) { w.WriteString("member"); w.WriteString(member); }
            w.WriteString("count"); w.WriteInt(count);
            w.WriteString("sh_degree"); w.WriteInt(0);
            w.WriteString("chunk"); w.WriteInt(chunk);
            w.WriteString("chunks"); w.WriteInt(chunks);
            w.WriteString("offset"); w.WriteInt(offset);
            w.WriteString("n"); w.WriteInt(n);
            float[] op = new float[n], sh = new float[3 * n], pos = new float[3 * n], rot = new float[4 * n], sc = new float[3 * n];
            for (int i = 0; i < n; i++) { op[i] = 1f; pos[3 * i] = baseX + offset + i; rot[4 * i + 3] = 1f; sc[3 * i] = sc[3 * i + 1] = sc[3 * i + 2] = 0.01f; }
            w.WriteString("opacity"); w.WriteFloat32Bin(op, 0, n);
            w.WriteString("sh"); w.WriteFloat32Bin(sh, 0, 3 * n);
            w.WriteString("position"); w.WriteFloat32Bin(pos, 0, 3 * n);
            w.WriteString("rotation"); w.WriteFloat32Bin(rot, 0, 4 * n);
            w.WriteString("scale"); w.WriteFloat32Bin(sc, 0, 3 * n);
            return Msg(w);
        }

        /// <summary>Dense f32 frame of a member (null: none, as v1) with position x = value for every Gaussian.</summary>
        static byte[] Frame(string member, int count, long seq, float value)
        {
            MsgPackWriter w = new MsgPackWriter();
            w.WriteMapHeader(member != null ? 9 : 8);
            w.WriteString("type"); w.WriteString("frame");
            if (member != null) { w.WriteString("member"); w.WriteString(member); }
            w.WriteString("seq"); w.WriteInt(seq);
            w.WriteString("t"); w.WriteInt(1000 + seq);
            w.WriteString("timing"); w.WriteMapHeader(0);
            w.WriteString("n"); w.WriteInt(count);
            float[] pos = new float[3 * count], rot = new float[4 * count], sc = new float[3 * count];
            for (int i = 0; i < count; i++) { pos[3 * i] = value; rot[4 * i + 3] = 1f; sc[3 * i] = 0.02f; }
            w.WriteString("position"); w.WriteFloat32Bin(pos, 0, 3 * count);
            w.WriteString("rotation"); w.WriteFloat32Bin(rot, 0, 4 * count);
            w.WriteString("scale"); w.WriteFloat32Bin(sc, 0, 3 * count);
            return Msg(w);
        }

        static string Feed(ClientConnection c, byte[] b, ServerMessage m)
        {
            try { c.Receive(b, 0, b.Length, m); return "ok"; }
            catch (ProtocolException e) { return e.Code + (e.Fatal ? " fatal" : " non-fatal"); }
        }

        static ClientConnection Connect(Hello h)
        {
            ClientConnection c = new ClientConnection();
            c.EncodeHello(h, new MsgPackWriter());
            return c;
        }

        public static void Unit(RunFn run, CheckFn check)
        {
            run("rooms: hello keys", delegate
            {
                Hello h = new Hello(); h.Layout = "ovr63"; h.Avatar = "default"; h.Room = "lab"; h.Publish = true; h.Self = false;
                MsgPackWriter w = new MsgPackWriter();
                ClientMessageEncoder.Hello(w, h);
                string hex = Hex(w.Buffer, 0, w.Length);
                check(hex.Contains(Hex(Encoding.ASCII.GetBytes("room"), 0, 4)) && !hex.Contains(Hex(Encoding.ASCII.GetBytes("publish"), 0, 7))
                      && !hex.Contains(Hex(Encoding.ASCII.GetBytes("self"), 0, 4)), "rooms: hello writes room; publish only when false, self only when true", hex);
                Hello v1 = new Hello(); v1.Layout = "ovr63"; v1.Publish = false; v1.Self = true; v1.RoomToken = "ab";
                w.Clear();
                ClientMessageEncoder.Hello(w, v1);
                check(!Hex(w.Buffer, 0, w.Length).Contains(Hex(Encoding.ASCII.GetBytes("publish"), 0, 7)), "rooms: without a room the room keys are not written", Hex(w.Buffer, 0, w.Length));
                string err = "(none)";
                Hello bad = new Hello(); bad.Layout = "ovr63"; bad.Room = "lab"; // publishing without an avatar
                w.Clear();
                ClientMessageEncoder.Hello(w, bad);
                try { new ClientMessageDecoder().Decode(w.Buffer, 0, w.Length, null, new ClientMessage()); }
                catch (ProtocolException e) { err = e.Code; }
                check(err == "bad_field" && Protocol.IsRoomName("lab-1.x_Y") && !Protocol.IsRoomName("a b") && !Protocol.IsRoomName(new string('a', 65)),
                      "rooms: a room hello without avatar is bad_field; room names are 1-64 of A-Z a-z 0-9 . _ -", err);
            });

            run("rooms: join, member avatars, routed frames, leave", delegate
            {
                Hello h = new Hello(); h.Layout = "ovr63"; h.Avatar = "default"; h.Coords = "unity"; h.Sparse = true; h.Room = "lab";
                ClientConnection c = Connect(h);
                ServerMessage m = new ServerMessage();
                FrameExchange ex = new FrameExchange();
                m.Frame = ex.DecodeTarget;
                check(Feed(c, RoomWelcome("lab", "me"), m) == "ok" && c.InRoom && c.Welcome.Room == "lab" && c.Welcome.Member == "me"
                      && c.State == ClientState.Streaming, "rooms: welcome.room and welcome.member decoded; streaming from welcome on", c.State.ToString());
                Feed(c, Join("alice", 3), m);
                string r1 = Feed(c, Chunk("alice", 3, 0, 1, 0, 3, 10f), m);
                check(r1 == "ok" && c.CompletedMember != null && c.CompletedMember.Id == "alice" && c.Member("alice").Avatar.Position[3] == 11f,
                      "rooms: a member's avatar assembled from its chunks", r1);
                Welcome mw = c.Welcome.ForMember(c.Member("alice").Join);
                check(mw.Count == 3 && mw.AvatarId == "default" && mw.Encoding == "f32" && mw.Sparse, "rooms: a member's welcome (session settings, member's avatar) for its sinks");
                string r3 = Feed(c, Frame("alice", 3, 5, 0.5f), m);
                check(r3 == "ok" && m.Frame.Member == "alice" && m.Frame.N == 3 && m.Frame.Position[0] == 0.5f, "rooms: a member's frame decoded with the member's count", r3);
                bool dropped = ex.Publish(m.Frame.Member);
                m.Frame = ex.DecodeTarget;
                Feed(c, Join("bob", 2), m);
                string r4 = Feed(c, Chunk("bob", 2, 0, 2, 0, 1, 20f), m);
                check(r4 == "ok" && c.CompletedMember == null, "rooms: first of two chunks does not complete the member");
                Feed(c, Chunk("bob", 2, 1, 2, 1, 1, 20f), m);
                check(c.CompletedMember != null && c.CompletedMember.Id == "bob" && c.Member("bob").Avatar.Position[3] == 21f, "rooms: chunks assembled in order");
                Feed(c, Frame("bob", 2, 9, 7f), m);
                ex.Publish(m.Frame.Member);
                m.Frame = ex.DecodeTarget;
                Feed(c, Frame("alice", 3, 6, 0.75f), m);
                bool dropped2 = ex.Publish(m.Frame.Member);
                m.Frame = ex.DecodeTarget;
                FrameData fa = ex.Take("alice"), fb = ex.Take("bob");
                check(!dropped && dropped2 && fa != null && fa.Seq == 6 && fa.Position[0] == 0.75f && fb != null && fb.Seq == 9 && ex.Take(null) == null,
                      "rooms: newest frame per member (alice's seq 5 replaced by 6), members kept apart");
                check(Feed(c, Frame(null, 2, 1, 1f), m) == "bad_field non-fatal", "rooms: a frame without member is dropped (non-fatal bad_field)");
                check(Feed(c, Chunk(null, 2, 0, 1, 0, 2, 0f), m) == "bad_field non-fatal", "rooms: an avatar chunk without member is dropped");
                check(Feed(c, Frame("alice", 2, 7, 1f), m) == "bad_length non-fatal", "rooms: a member frame with the wrong count is a non-fatal bad_length");
                check(Feed(c, Frame("carol", 3, 1, 1f), m) == "not_ready non-fatal" && c.State == ClientState.Streaming, "rooms: a frame for an unknown member is dropped (non-fatal not_ready)");
                check(Feed(c, Chunk("carol", 1, 0, 1, 0, 1, 0f), m) == "not_ready non-fatal", "rooms: an avatar chunk before the member's join is dropped");
                Feed(c, Join("dave", -1), m);
                check(c.Member("dave") != null && !c.Member("dave").Join.Publish && c.Member("dave").Avatar == null, "rooms: a watch-only member's join (no avatar)");
                check(Feed(c, Chunk("dave", 1, 0, 1, 0, 1, 0f), m) == "bad_field non-fatal" && Feed(c, Frame("dave", 1, 1, 1f), m) == "not_ready non-fatal",
                      "rooms: a watch-only member's chunks and frames are dropped");
                Feed(c, Leave("alice", "bye"), m);
                check(c.LeftMember != null && c.LeftMember.Id == "alice" && c.Member("alice") == null && m.Leave.Reason == "bye", "rooms: leave removes the member");
                ex.Drop("alice");
                check(Feed(c, Frame("alice", 3, 8, 1f), m) == "not_ready non-fatal", "rooms: frames after leave are dropped");
                Feed(c, Leave("nobody", "closed"), m);
                check(c.LeftMember == null && c.MemberCount == 2, "rooms: leave of an unknown member is ignored");
                Feed(c, Join("bob", 4), m);
                check(Feed(c, Frame("bob", 4, 1, 1f), m) == "not_ready non-fatal" && c.Member("bob").Avatar.Count == 4,
                      "rooms: a re-join replaces the member; frames wait for its new avatar");
            });

            run("rooms: watch-only session", delegate
            {
                Hello h = new Hello(); h.Layout = "ovr63"; h.Coords = "unity"; h.Room = "lab"; h.Publish = false;
                ClientConnection c = Connect(h);
                ServerMessage m = new ServerMessage();
                m.Frame = new FrameData();
                string r = Feed(c, RoomWelcome("lab", "w1", false), m);
                check(r == "ok" && c.State == ClientState.Streaming && c.Welcome.AvatarId == null && c.Welcome.Count == 0,
                      "rooms: a watch-only welcome has no avatar and streams at once", r);
                Feed(c, Join("alice", 1), m);
                Feed(c, Chunk("alice", 1, 0, 1, 0, 1, 3f), m);
                check(Feed(c, Frame("alice", 1, 0, 2f), m) == "ok" && m.Frame.Member == "alice", "rooms: a watcher receives members' frames");
                string err = "(none)";
                try { new ServerMessageDecoder().Decode(RoomWelcome(null, null, false), 0, RoomWelcome(null, null, false).Length, null, new ServerMessage()); }
                catch (ProtocolException e) { err = e.Code; }
                check(err == "bad_field", "rooms: outside a room a welcome without avatar is bad_field", err);
            });

            run("rooms: join/leave cycles allocate no frames", delegate
            {
                FrameExchange ex = new FrameExchange();
                // one life of a member: two frames published, the newest taken, then it leaves (receive thread)
                // and the main thread takes its Left event (OferaClient.TryTakeRoomEvent -> Release)
                Action<string, bool> life = (member, release) =>
                {
                    ex.Publish(member); ex.Publish(member);
                    FrameData held = ex.Take(member);
                    ex.Publish(null); ex.Take(null);
                    ex.Drop(member);
                    for (int k = 0; k < 3; k++)  // while parked, the held frame is never decoded into
                    {
                        if (ReferenceEquals(ex.DecodeTarget, held)) throw new Exception("a departed member's held frame was reused before its release");
                        ex.Publish("other"); ex.Take("other");
                    }
                    if (release) ex.Release(member);
                };
                for (int i = 0; i < 4; i++) life("warm" + i, true);
                int warm = ex.Allocated;
                for (int i = 0; i < 200; i++) life("m" + i, true);  // a new id each time
                check(ex.Allocated == warm && ex.ParkedCount == 0,
                      "rooms: 200 join/leave cycles (Left taken) allocate no FrameData", warm + " -> " + ex.Allocated);
                for (int i = 0; i < 200; i++) life("again", false);  // the same id rejoining: its next Take recycles
                check(ex.Allocated == warm && ex.ParkedCount <= 1, "rooms: a member rejoining reuses its last life's frame",
                      warm + " -> " + ex.Allocated + ", parked " + ex.ParkedCount);
                ex.Release("again");
                for (int session = 2; session < 100; session++)  // new sessions with members holding frames
                {
                    ex.Publish("a"); ex.Publish("b"); ex.Take("a"); ex.Take("b");
                    ex.Reset(session);
                    ex.ReleaseBefore(session);  // the main thread sees the new session (an event or avatar of it)
                }
                check(ex.Allocated == warm && ex.ParkedCount == 0,
                      "rooms: new sessions with held member frames allocate no FrameData",
                      warm + " -> " + ex.Allocated + ", parked " + ex.ParkedCount);
            });

            run("rooms: v1 sessions are unchanged", delegate
            {
                Hello h = new Hello(); h.Layout = "ovr63"; h.Coords = "unity"; h.Sparse = true;
                ClientConnection c = Connect(h);
                ServerMessage m = new ServerMessage();
                m.Frame = new FrameData();
                Feed(c, RoomWelcome(null, null), m);
                check(!c.InRoom && c.Welcome.Room == null && c.State == ClientState.ReceivingAvatar, "rooms: welcome without room is v1");
                check(Feed(c, Frame(null, 2, 1, 1f), m) == "not_ready fatal", "rooms: outside a room a frame before the avatar stays fatal");
            });
        }
        // ============================================================ live: a room of `ofera serve`

        /// <summary>The Python publisher: joins the room with `ofera.client`, prints "member ID", publishes jawOpen at
        /// about 30 Hz (and reads what the room sends it) until a line arrives on stdin, then says bye and prints
        /// "bye N" (N bs sent).</summary>
        const string PythonPublisher = @"
import asyncio, sys
import numpy as np
from ofera.client import connect

async def main(url, room):
    c = await connect(url, room=room, avatar='default', max_gaussians=5000)
    print('member', c.member, flush=True)
    stop = asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)

    async def read():
        while True:
            await c.recv()

    reader = asyncio.create_task(read())
    w, k = np.zeros(52, np.float32), 0
    while not stop.done():
        w[17] = 0.5 + 0.5 * np.sin(k / 5)
        await c.send_bs(w)
        k += 1
        await asyncio.sleep(1 / 30)
    reader.cancel()
    await c.close()
    print('bye', k, flush=True)

asyncio.run(main(sys.argv[1], sys.argv[2]))
";

        static OferaClient RoomClient(string url, string room, bool publish, bool self)
        {
            OferaClientOptions o = new OferaClientOptions();
            o.Url = url; o.Layout = "ovr63"; o.Encoding = "q13"; o.Sparse = true; o.Coords = "unity";
            o.Room = room; o.Publish = publish; o.Self = self; o.MaxGaussians = 5000; o.PingIntervalSeconds = 0;
            o.HandshakeTimeoutSeconds = 120;
            OferaClient c = new OferaClient(o);
            c.Start();
            return c;
        }

        /// <summary>Takes room events until one matches (true) or the time is up; every event seen goes to <paramref name="seen"/>.</summary>
        static RoomEvent AwaitEvent(OferaClient c, Func<RoomEvent, bool> match, double seconds, List<RoomEvent> seen, WaitFn waitFor)
        {
            RoomEvent found = null;
            waitFor(delegate
            {
                RoomEvent e;
                while (found == null && c.TryTakeRoomEvent(out e)) { seen.Add(e); if (match(e)) found = e; }
                return found != null;
            }, seconds, c, new List<ClientEvent>());
            return found;
        }

        /// <summary>Frames of one member taken by the main thread until <paramref name="want"/> arrived: each checked
        /// (member, session, finite values) and applied to that member's GaussianState.</summary>
        static string TakeFrames(OferaClient c, RoomEvent joined, int want, double seconds, WaitFn waitFor, out int got)
        {
            GaussianState st = new GaussianState(joined.Avatar);
            string problems = "";
            int n = 0;
            long lastSeq = -1;
            waitFor(delegate
            {
                FrameData f = c.TryTakeFrame(joined.Member);
                if (f == null) return n >= want;
                n++;
                if (f.Member != joined.Member) problems += " member " + f.Member;
                if (f.SessionNumber != joined.Session) problems += " session " + f.SessionNumber;
                if (f.Seq <= lastSeq) problems += " seq " + f.Seq + " after " + lastSeq;
                lastSeq = f.Seq;
                for (int i = 0; i < 3 * f.N; i++) if (float.IsNaN(f.Position[i]) || float.IsInfinity(f.Position[i])) { problems += " non-finite"; break; }
                if (f.HasIndex ? f.N > joined.Avatar.Count : f.N != joined.Avatar.Count) problems += " n " + f.N;
                st.Apply(f);
                return n >= want;
            }, seconds, c, new List<ClientEvent>());
            got = n;
            return problems;
        }

        public static void Live(string url, string python, RunFn run, CheckFn check, WaitFn waitFor)
        {
            run("live room: a C# watcher, a Python publisher, a C# publisher seeing itself", delegate { LiveRoom(url, python, check, waitFor); });
        }

        static void LiveRoom(string url, string python, CheckFn check, WaitFn waitFor)
        {
            if (python == null) { check(false, "live room: needs python with the ofera package (run.sh passes --python)"); return; }
            string room = "cs-" + Guid.NewGuid().ToString("N").Substring(0, 8);
            List<RoomEvent> seen = new List<RoomEvent>();
            OferaClient watcher = RoomClient(url, room, false, false);
            Process py = null;
            OferaClient pub = null;
            try
            {
                bool up = waitFor(() => watcher.Status == ClientStatus.Streaming && watcher.Member != null, 120, watcher, new List<ClientEvent>());
                check(up, "live room: watch-only hello -> welcome with a member id, streaming at once", "status " + watcher.Status);
                if (!up) return;

                ProcessStartInfo psi = new ProcessStartInfo(python);
                psi.Arguments = "-c \"" + PythonPublisher.Replace("\"", "\\\"") + "\" " + url + " " + room;
                psi.UseShellExecute = false; psi.RedirectStandardInput = true; psi.RedirectStandardOutput = true;
                py = Process.Start(psi);
                System.Threading.Tasks.Task<string> first = py.StandardOutput.ReadLineAsync();
                string line = first.Wait(120000) ? first.Result : null;
                string pyMember = line != null && line.StartsWith("member ") ? line.Substring(7) : null;
                check(pyMember != null, "live room: the Python client joined the room", line ?? "(no line)");
                if (pyMember == null) return;

                RoomEvent joined = AwaitEvent(watcher, e => e.Kind == RoomEventKind.Joined && e.Member == pyMember, 60, seen, waitFor);
                check(joined != null && joined.Avatar != null && joined.Join.AvatarId == "default" && joined.Avatar.Count > 0 && joined.Avatar.Count <= 5000
                      && joined.Welcome.Count == joined.Avatar.Count && joined.Welcome.Quant != null && joined.Session == watcher.SessionNumber,
                      "live room: the Python member's join and complete avatar (reduced to max_gaussians, q13 quant of its own)",
                      joined == null ? "events " + string.Join(", ", seen) : joined.Avatar.Count + " Gaussians");
                if (joined == null) return;
                int got;
                string problems = TakeFrames(watcher, joined, 10, 60, waitFor, out got);
                check(got >= 10 && problems.Length == 0, "live room: the Python member's frames, with its member id, applied", got + " frames" + problems);

                // a C# publisher with self: sees its own avatar as a member; the watcher sees it too
                pub = RoomClient(url, room, true, true);
                bool pubUp = waitFor(() => pub.Status == ClientStatus.Streaming && pub.Member != null, 120, pub, new List<ClientEvent>());
                check(pubUp, "live room: publishing hello -> welcome", "status " + pub.Status);
                List<RoomEvent> pubSeen = new List<RoomEvent>();
                float[] w = new float[63];
                int k = 0;
                RoomEvent selfJoin = null;
                waitFor(delegate
                {
                    w[24] = (float)(0.5 + 0.5 * Math.Sin(k++ * 0.2)); // JAW_DROP
                    pub.SubmitBlendshapes(w, OferaClock.NowMicros());
                    RoomEvent e;
                    while (pub.TryTakeRoomEvent(out e)) { pubSeen.Add(e); if (e.Kind == RoomEventKind.Joined && e.Member == pub.Member) selfJoin = e; }
                    System.Threading.Thread.Sleep(14);
                    return selfJoin != null;
                }, 60, pub, new List<ClientEvent>());
                check(selfJoin != null && selfJoin.Avatar != null, "live room: with self, one's own avatar arrives as a member (join + avatar)",
                      "events " + string.Join(", ", pubSeen));
                check(pubSeen.Exists(e => e.Member == pyMember && e.Avatar != null) && pubSeen.Exists(e => e.Member == watcher.Member && e.Avatar == null && !e.Join.Publish),
                      "live room: the publisher hears of the Python member and of the watcher (watch-only: no avatar)", "events " + string.Join(", ", pubSeen));
                if (selfJoin != null)
                {
                    int own = 0;
                    string ownProblems = "";
                    waitFor(delegate
                    {
                        w[24] = (float)(0.5 + 0.5 * Math.Sin(k++ * 0.2));
                        pub.SubmitBlendshapes(w, OferaClock.NowMicros());
                        FrameData f = pub.TryTakeFrame(pub.Member);
                        if (f != null) { own++; if (f.Member != pub.Member) ownProblems += " member " + f.Member; }
                        System.Threading.Thread.Sleep(14);
                        return own >= 5;
                    }, 60, pub, new List<ClientEvent>());
                    check(own >= 5 && ownProblems.Length == 0, "live room: one's own frames come back with one's own member id", own + " frames" + ownProblems);
                }
                RoomEvent pubJoin = AwaitEvent(watcher, e => e.Kind == RoomEventKind.Joined && e.Member == pub.Member, 60, seen, waitFor);
                check(pubJoin != null && pubJoin.Avatar != null, "live room: the watcher sees the C# publisher join", "events " + string.Join(", ", seen));

                // the Python client leaves: its Left reaches the watcher within 3 s, reason bye
                Stopwatch sw = Stopwatch.StartNew();
                py.StandardInput.WriteLine("bye");
                py.StandardInput.Flush();
                RoomEvent left = AwaitEvent(watcher, e => e.Kind == RoomEventKind.Left && e.Member == pyMember, 10, seen, waitFor);
                double leftS = sw.Elapsed.TotalSeconds;
                check(left != null && left.Reason == "bye" && leftS < 3, "live room: the Python member's leave (reason bye) within 3 s",
                      left == null ? "events " + string.Join(", ", seen) : left.Reason + " after " + leftS.ToString("F2") + " s");
                check(watcher.TryTakeFrame(pyMember) == null, "live room: no frame of a member after its Left was taken");

                // the C# publisher stops: the watcher hears it left
                pub.Stop();
                RoomEvent pubLeft = AwaitEvent(watcher, e => e.Kind == RoomEventKind.Left && e.Member == pubJoin.Member, 10, seen, waitFor);
                check(pubLeft != null && pubLeft.Reason == "bye", "live room: the C# publisher's Stop (bye) -> leave reason bye",
                      pubLeft == null ? "events " + string.Join(", ", seen) : pubLeft.Reason);
            }
            finally
            {
                if (pub != null) pub.Stop();
                watcher.Stop();
                if (py != null)
                {
                    try { if (!py.HasExited) { py.StandardInput.WriteLine("bye"); if (!py.WaitForExit(10000)) py.Kill(); } }
                    catch (InvalidOperationException) { }
                    py.Dispose();
                }
            }
        }
    }
}
