// Message types of protocol v1. Large arrays live in reusable containers (AvatarData, FrameData)
// that decoders fill in place. UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    public enum ServerMessageKind { None, Welcome, Avatar, Frame, Error, Pong, Join, Leave, Rig }
    public enum ClientMessageKind { None, Hello, Blendshapes, Ping, Bye, Resync }

    /// <summary>Client -> server `hello`. Null fields are omitted on the wire (the server's defaults apply).</summary>
    public sealed class Hello
    {
        public int Protocol = Ofera.Client.Protocol.Version;
        public string Layout = "ovr63";
        public string Avatar;          // null: omitted ("default")
        public string Encoding;        // null: omitted ("f32")
        public string Coords;          // null: omitted ("flame")
        public bool? Sparse;
        /// <summary>Ask for key and delta frames (f16, q13; PROTOCOL.md 7.1). Only true is written.</summary>
        public bool? Delta;
        public string Device;
        public string Token;
        public long? MaxGaussians;
        /// <summary>Rooms (PROTOCOL.md 12; a server without rooms ignores them): room to join (1-64 of A-Z a-z 0-9 . _ -),
        /// publish (default true; false: watch only), self (default false: also receive one's own avatar), room_token
        /// (hex HMAC-SHA256 of the room name, if the server has a room secret). Written only with a room.</summary>
        public string Room;
        public bool? Publish;
        public bool? Self;
        public string RoomToken;
    }

    /// <summary>Client -> server `bs` (as decoded by a server; a client encodes from its own arrays).</summary>
    public sealed class Blendshapes
    {
        public long Seq;
        public long T;
        public float[] W = new float[0];
        public int Count;
    }

    /// <summary>Session format announced by `welcome`: what a receiver needs to decode frames.</summary>
    public sealed class FrameFormat
    {
        public FrameEncoding Encoding;
        public int Count;
        public bool Sparse;
        public Quant Quant; // only for q13
        /// <summary>A delta session's held codes (PROTOCOL.md 7.1, Delta.cs); null: frames are self-contained.</summary>
        public DeltaState Delta;
        /// <summary>A params session (PROTOCOL.md 13): frames carry 68 values, the client deforms (Rig.cs).</summary>
        public bool Params;

        public FrameFormat() { }
        public FrameFormat(FrameEncoding encoding, int count, bool sparse, Quant quant)
        {
            Encoding = encoding; Count = count; Sparse = sparse; Quant = quant;
        }
    }

    public sealed class Welcome
    {
        public int Protocol;
        public string Session;
        public string AvatarId;
        public int Count;
        public int ShDegree;
        public string Layout;
        public string Encoding;
        public string Coords;
        public bool Sparse;
        /// <summary>Frames are key and delta frames (PROTOCOL.md 7.1); ToFormat gives the session its DeltaState.</summary>
        public bool Delta;
        public Quant Quant;     // null unless encoding q13
        public string Server;   // optional
        /// <summary>Params sessions (PROTOCOL.md 13): the rig body's size in bytes; null otherwise.</summary>
        public long? RigBytes;
        /// <summary>Rooms (PROTOCOL.md 12.2): the room joined and this client's member id; null without a room. A room
        /// session's welcome has no quant (each join carries its own), and no avatar for a watch-only member
        /// (AvatarId null, Count 0).</summary>
        public string Room;
        public string Member;

        /// <summary>Rooms: this session's settings with a member's avatar (count, sh_degree, and quant if the join has its own).</summary>
        public Welcome ForMember(JoinMessage j)
        {
            Welcome w = (Welcome)MemberwiseClone();
            w.AvatarId = j.AvatarId;
            w.Count = j.Count;
            w.ShDegree = j.ShDegree;
            if (j.Quant != null) w.Quant = j.Quant;
            return w;
        }

        public FrameFormat ToFormat()
        {
            if (Encoding == ParamsProtocol.Encoding) return new FrameFormat(FrameEncoding.F32, Count, false, null) { Params = true };
            FrameEncoding e;
            Ofera.Client.Protocol.TryParseEncoding(Encoding, out e);
            FrameFormat f = new FrameFormat(e, Count, Sparse, e == FrameEncoding.Q13 ? Quant : null);
            if (Delta) f.Delta = new DeltaState(e, Count, f.Quant);
            return f;
        }
    }

    /// <summary>Header of one `avatar` chunk; its arrays are copied into an <see cref="AvatarData"/>.</summary>
    public struct AvatarChunkHeader
    {
        public int Count, ShDegree, Chunk, Chunks, Offset, N;
        /// <summary>Rooms: whose avatar the chunk belongs to (null: the session's own avatar, v1).</summary>
        public string Member;
    }

    /// <summary>The whole static avatar (session coordinates): N Gaussians, float32, row-major.</summary>
    public sealed class AvatarData
    {
        public readonly int Count;
        public readonly int ShDegree;
        /// <summary>Coefficients per colour channel, (deg+1)^2.</summary>
        public readonly int K;
        public readonly float[] Opacity;   // N
        public readonly float[] Sh;        // N x K x 3
        public readonly float[] Position;  // N x 3
        public readonly float[] Rotation;  // N x 4 (x, y, z, w)
        public readonly float[] Scale;     // N x 3
        /// <summary>Params sessions: the rig that deforms this avatar (complete before the avatar is handed over); else null.</summary>
        public RigData Rig;

        public AvatarData(int count, int shDegree)
        {
            if (count < 0) throw new ArgumentOutOfRangeException("count");
            if (shDegree < 0 || shDegree > Ofera.Client.Protocol.MaxShDegree) throw new ArgumentOutOfRangeException("shDegree");
            Count = count;
            ShDegree = shDegree;
            K = Ofera.Client.Protocol.ShCoefficients(shDegree);
            Opacity = new float[count];
            Sh = new float[(long)count * K * 3];
            Position = new float[3L * count];
            Rotation = new float[4L * count];
            Scale = new float[3L * count];
        }
    }

    /// <summary>
    /// One decoded `frame`, in a reusable container: arrays grow to the largest n seen and are reused.
    /// Sparse frames carry <see cref="Index"/> (HasIndex); dense frames carry every Gaussian in order.
    /// </summary>
    public sealed class FrameData
    {
        public long Seq;
        public long T;
        public int N;
        public bool HasIndex;
        /// <summary>Delta sessions: a key frame (dense) or a delta frame (HasIndex: the changed Gaussians).</summary>
        public bool IsKey;
        /// <summary>Rooms: whose avatar the frame moves (null: the session's own avatar, v1). Interned by the decoder.</summary>
        public string Member;
        /// <summary>False when the decoder only kept the payload (GPU upload path): Position/Rotation/Scale are not filled.</summary>
        public bool HasValues = true;
        /// <summary>The arrays as they arrived, when the decoder keeps payloads (<see cref="ServerMessageDecoder.KeepPayload"/>).</summary>
        public readonly FramePayload Payload = new FramePayload();
        public uint[] Index = new uint[0];
        public float[] Position = new float[0]; // N x 3
        public float[] Rotation = new float[0]; // N x 4
        public float[] Scale = new float[0];    // N x 3
        /// <summary>Params sessions: the frame's 68 values (HasParams); Position/Rotation/Scale then hold the client's
        /// own deformation of the rig's Gaussians (Index = the rig's index) when HasValues.</summary>
        public readonly float[] Params = new float[ParamsProtocol.Length];
        public bool HasParams;
        /// <summary>False for an unstamped params frame (no seq, t, timing: Seq and T are then 0).</summary>
        public bool Stamped = true;

        public int TimingCount;
        public readonly string[] TimingNames = new string[Ofera.Client.Protocol.MaxTimingStages];
        public readonly long[] TimingValues = new long[Ofera.Client.Protocol.MaxTimingStages];

        /// <summary>Client clock (µs) when the message was received; set by the client, not the codec.</summary>
        public long ReceivedAt;
        /// <summary>Session number (increments per connection) the frame belongs to; set by the client.</summary>
        public int SessionNumber;

        public int Capacity { get { return Index.Length; } }

        public void EnsureCapacity(int n)
        {
            if (n <= Index.Length) return;
            Index = new uint[n];
            Position = new float[3L * n];
            Rotation = new float[4L * n];
            Scale = new float[3L * n];
        }

        /// <summary>Value of a timing stage, or -1 if absent.</summary>
        public long Timing(string stage)
        {
            for (int i = 0; i < TimingCount; i++) if (TimingNames[i] == stage) return TimingValues[i];
            return -1;
        }

        public void CopyFrom(FrameData o)
        {
            Seq = o.Seq; T = o.T; N = o.N; HasIndex = o.HasIndex; IsKey = o.IsKey; Member = o.Member; HasValues = o.HasValues;
            HasParams = o.HasParams; Stamped = o.Stamped;
            if (o.HasParams) Array.Copy(o.Params, Params, ParamsProtocol.Length);
            EnsureCapacity(o.N);
            if (o.HasIndex) Array.Copy(o.Index, Index, o.N);
            if (o.HasValues)
            {
                Array.Copy(o.Position, Position, 3 * o.N);
                Array.Copy(o.Rotation, Rotation, 4 * o.N);
                Array.Copy(o.Scale, Scale, 3 * o.N);
            }
            Payload.CopyFrom(o.Payload);
            TimingCount = o.TimingCount;
            Array.Copy(o.TimingNames, TimingNames, o.TimingCount);
            Array.Copy(o.TimingValues, TimingValues, o.TimingCount);
            ReceivedAt = o.ReceivedAt;
            SessionNumber = o.SessionNumber;
        }
    }

    public sealed class ErrorMessage
    {
        public string Code;
        public string Message;
        public bool Fatal;
        public long? Seq;

        public override string ToString()
        {
            return Code + (Fatal ? " (fatal)" : "") + ": " + Message + (Seq.HasValue ? " [seq " + Seq.Value + "]" : "");
        }
    }

    /// <summary>Rooms: `join` {member, avatar {id, count, sh_degree}, quant?, publish?}; a publishing member's `avatar`
    /// chunks follow. A watch-only member (Publish false) has no avatar (AvatarId null) and sends no frames.</summary>
    public sealed class JoinMessage
    {
        public string Member;
        public bool Publish = true;
        public string AvatarId;
        public int Count;
        public int ShDegree;
        /// <summary>q13 parameters of this member's stream if the server sends them (else the session's welcome.quant).</summary>
        public Quant Quant;
    }

    /// <summary>Rooms: `leave` {member, reason}.</summary>
    public sealed class LeaveMessage
    {
        public string Member;
        public string Reason;
    }

    /// <summary>Holder of the latest decoded server message of each kind (reused; no per-message allocation for frames).</summary>
    public sealed class ServerMessage
    {
        public ServerMessageKind Kind;
        public Welcome Welcome;
        public AvatarChunkHeader Avatar;
        public FrameData Frame;
        public ErrorMessage Error;
        public long PongT;
        public JoinMessage Join;
        public LeaveMessage Leave;
        /// <summary>Params sessions: the `rig` chunk's header (its data stays in the input buffer).</summary>
        public RigChunkHeader Rig;
    }

    /// <summary>Holder of a decoded client message (used by tests and by any C# server).</summary>
    public sealed class ClientMessage
    {
        public ClientMessageKind Kind;
        public Hello Hello;
        public Blendshapes Blendshapes = new Blendshapes();
        public long PingT;
    }
}
