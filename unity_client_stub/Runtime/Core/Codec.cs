// Strict decoders and encoders of every protocol v1 message, mirroring the Python reference
// (protocol/ofera_protocol/codec.py): same checks, same order, same error codes.
// Decoding allocates nothing per frame once the containers have grown. UnityEngine-free, C# 7.2.
using System;
using System.Text;

namespace Ofera.Client
{
    /// <summary>Field names the decoders know, and allocation-free key lookup.</summary>
    internal static class Keys
    {
        public const int Type = 0, Protocol_ = 1, Layout = 2, Avatar = 3, Encoding_ = 4, Coords = 5, Sparse = 6,
            Device = 7, Token = 8, MaxGaussians = 9, Seq = 10, T = 11, W = 12, Session = 13, Quant_ = 14,
            Server = 15, Count = 16, ShDegree = 17, Chunk = 18, Chunks = 19, Offset = 20, N = 21, Opacity = 22,
            Sh = 23, Position = 24, Rotation = 25, Scale = 26, Timing = 27, Index = 28, Code = 29, Message = 30,
            Fatal = 31, Id = 32, PosMin = 33, PosMax = 34, LogScale = 35, Room = 36, Member = 37, Reason = 38,
            Delta = 39, Key = 40, Changed = 41, Wide = 42, PositionDelta = 43, MovedPosition = 44, MovedRotation = 45,
            MovedScale = 46,
            // params sessions (PROTOCOL.md 13): `rig` chunks, the rig body (Rig.cs), params frames, welcome.rig_bytes
            Size = 47, Data = 48, Params = 49, RigBytes = 50, Binding = 51, Vertices = 52, Faces = 53, Gaussians = 54,
            ExprDims = 55, JointsKey = 56, JointsExpr = 57, Template = 58, ExprBasis = 59, PoseRows = 60, PoseBasis = 61,
            Weights = 62, Face = 63, GaussianFace = 64, LocalPosition = 65, Bary = 66, NormalOffset = 67,
            LocalRotation = 68, LocalScale = 69,
            // rooms (PROTOCOL.md 12): hello.publish, hello.self, hello.room_token
            Publish = 70, Self = 71, RoomToken = 72;
        public const int KeyCount = 73;

        public static readonly string[] Names =
        {
            "type", "protocol", "layout", "avatar", "encoding", "coords", "sparse", "device", "token",
            "max_gaussians", "seq", "t", "w", "session", "quant", "server", "count", "sh_degree", "chunk",
            "chunks", "offset", "n", "opacity", "sh", "position", "rotation", "scale", "timing", "index",
            "code", "message", "fatal", "id", "pos_min", "pos_max", "log_scale", "room", "member", "reason",
            "delta", "key", "changed", "wide", "position_delta", "moved_position", "moved_rotation", "moved_scale",
            "size", "data", "params", "rig_bytes", "binding", "vertices", "faces", "gaussians", "expr_dims", "joints",
            "joints_expr", "template", "expr_basis", "pose_rows", "pose_basis", "weights", "face", "gaussian_face",
            "local_position", "bary", "normal_offset", "local_rotation", "local_scale",
            "publish", "self", "room_token",
        };

        public static readonly byte[][] Utf8 = MakeUtf8();

        static byte[][] MakeUtf8()
        {
            byte[][] r = new byte[Names.Length][];
            for (int i = 0; i < Names.Length; i++) r[i] = System.Text.Encoding.ASCII.GetBytes(Names[i]);
            return r;
        }

        public static int Find(byte[] buf, int off, int len)
        {
            for (int k = 0; k < KeyCount; k++)
            {
                byte[] name = Utf8[k];
                if (name.Length != len) continue;
                int i = 0;
                while (i < len && buf[off + i] == name[i]) i++;
                if (i == len) return k;
            }
            return -1;
        }
    }

    /// <summary>
    /// Shared machinery: validation, map scanning into key slots (value position or -1; nil counts as
    /// absent, the last duplicate wins, unknown keys are ignored) and strict field getters.
    /// </summary>
    public abstract class MessageDecoderBase
    {
        internal readonly MsgPackReader R = new MsgPackReader();
        internal readonly int[] Top = new int[Keys.KeyCount];
        internal readonly int[] Sub = new int[Keys.KeyCount];

        internal static ProtocolException Err(string code, string message) { return new ProtocolException(code, message); }

        /// <summary>Validates the message and scans its top-level map into <see cref="Top"/>.</summary>
        internal void Begin(byte[] buf, int offset, int count, int maxSize)
        {
            if (count > maxSize)
                throw Err(ErrorCodes.MessageTooLarge, "message of " + count + " bytes exceeds the limit of " + maxSize);
            R.Reset(buf, offset, count);
            R.Validate();
            Scan(offset, Top);
        }

        internal void Scan(int mapPosition, int[] slots)
        {
            for (int i = 0; i < slots.Length; i++) slots[i] = -1;
            R.Position = mapPosition;
            int n = R.ReadMapHeader();
            for (int i = 0; i < n; i++)
            {
                int ko, kl;
                R.ReadStringSegment(out ko, out kl);
                int k = Keys.Find(R.Buffer, ko, kl);
                int vpos = R.Position;
                bool nil = R.PeekType() == MsgType.Nil;
                R.Skip();
                if (k >= 0) slots[k] = nil ? -1 : vpos;
            }
        }

        internal static int CodePoints(byte[] b, int off, int len)
        {
            int n = 0;
            for (int i = 0; i < len; i++) if ((b[off + i] & 0xc0) != 0x80) n++;
            return n;
        }

        internal string TypeAt(int pos) { R.Position = pos; return R.PeekTypeName(); }

        internal bool Present(int[] s, int k) { return s[k] >= 0; }

        internal long GetInt(int[] s, int k, string where, long lo, long hi)
        {
            long? v = GetOptInt(s, k, where, lo, hi);
            if (!v.HasValue) throw Err(ErrorCodes.BadField, where + ": missing field '" + Keys.Names[k] + "'");
            return v.Value;
        }

        internal long? GetOptInt(int[] s, int k, string where, long lo, long hi)
        {
            if (s[k] < 0) return null;
            R.Position = s[k];
            if (R.PeekType() != MsgType.Int)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must be an int, got " + R.PeekTypeName());
            bool overflow;
            long v = R.ReadInteger(out overflow);
            if (overflow || v < lo || v > hi)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' = " + (overflow ? "(above 2^63-1)" : v.ToString()) + " is outside [" + lo + ", " + hi + "]");
            return v;
        }

        /// <summary>String field of minLen..maxLen characters; null if absent and not required.</summary>
        internal string GetStr(int[] s, int k, string where, bool required, int maxLen = Protocol.MaxIdLength, int minLen = 1)
        {
            if (s[k] < 0)
            {
                if (required) throw Err(ErrorCodes.BadField, where + ": missing field '" + Keys.Names[k] + "'");
                return null;
            }
            R.Position = s[k];
            if (R.PeekType() != MsgType.Str)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must be a str, got " + R.PeekTypeName());
            int off, len;
            R.ReadStringSegment(out off, out len);
            int cp = CodePoints(R.Buffer, off, len);
            if (cp < minLen || cp > maxLen)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must have " + minLen + ".." + maxLen + " characters, got " + cp);
            R.Position = s[k];
            return R.ReadString();
        }

        /// <summary>String that must be one of <paramref name="choices"/> (else error <paramref name="code"/>); dflt when absent (null: required).</summary>
        internal string GetChoice(int[] s, int k, string where, string[] choices, string code, string dflt)
        {
            string v = GetStr(s, k, where, dflt == null);
            if (v == null) v = dflt;
            if (!Protocol.Contains(choices, v))
                throw Err(code, where + ": " + Keys.Names[k] + " '" + v + "' is not one of " + string.Join(", ", choices));
            return v;
        }

        internal bool? GetOptBool(int[] s, int k, string where)
        {
            if (s[k] < 0) return null;
            R.Position = s[k];
            if (R.PeekType() != MsgType.Bool)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must be a bool, got " + R.PeekTypeName());
            return R.ReadBool();
        }

        internal bool GetBool(int[] s, int k, string where)
        {
            bool? v = GetOptBool(s, k, where);
            if (!v.HasValue) throw Err(ErrorCodes.BadField, where + ": missing field '" + Keys.Names[k] + "'");
            return v.Value;
        }

        /// <summary>Position of a nested map, or -1 if absent and not required.</summary>
        internal int GetMap(int[] s, int k, string where, bool required)
        {
            if (s[k] < 0)
            {
                if (required) throw Err(ErrorCodes.BadField, where + ": missing field '" + Keys.Names[k] + "'");
                return -1;
            }
            R.Position = s[k];
            if (R.PeekType() != MsgType.Map)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must be a map, got " + R.PeekTypeName());
            return s[k];
        }

        /// <summary>A bin field's payload; false if absent and not required.</summary>
        internal bool GetBin(int[] s, int k, string where, bool required, out int offset, out int length)
        {
            offset = 0; length = 0;
            if (s[k] < 0)
            {
                if (required) throw Err(ErrorCodes.BadField, where + ": missing field '" + Keys.Names[k] + "'");
                return false;
            }
            R.Position = s[k];
            if (R.PeekType() != MsgType.Bin)
                throw Err(ErrorCodes.BadField, where + ": field '" + Keys.Names[k] + "' must be bin, got " + R.PeekTypeName());
            R.ReadBinSegment(out offset, out length);
            return true;
        }

        /// <summary>A bin field of exactly <paramref name="elements"/> x <paramref name="elemSize"/> bytes (bad_length otherwise).</summary>
        internal bool GetArray(int[] s, int k, string where, int elemSize, long elements, bool required, out int offset, string dtype)
        {
            int length;
            if (!GetBin(s, k, where, required, out offset, out length)) return false;
            long need = elements * elemSize;
            if (length != need)
                throw Err(ErrorCodes.BadLength, where + ": field '" + Keys.Names[k] + "' has " + length + " bytes, expected " + need + " (" + elements + " " + dtype + ")");
            return true;
        }

        /// <summary>Checks that <paramref name="count"/> float32 at offset are finite (non_finite otherwise).</summary>
        internal void CheckFiniteF32(int offset, long count, string where, int k)
        {
            byte[] b = R.Buffer;
            for (long i = 0; i < count; i++)
            {
                if ((BitCast.ReadUInt32LE(b, (int)(offset + 4 * i)) & 0x7f800000u) == 0x7f800000u)
                    throw Err(ErrorCodes.NonFinite, where + ": field '" + Keys.Names[k] + "' holds NaN or infinity");
            }
        }

        internal string ReadType(string[] known, string direction)
        {
            string t = GetStr(Top, Keys.Type, "message", true);
            if (!Protocol.Contains(known, t))
                throw Err(ErrorCodes.UnknownType, "unknown " + direction + " message type '" + t + "'; expected one of " + string.Join(", ", known));
            return t;
        }
    }

    /// <summary>
    /// Decodes server -> client messages. One instance per receive thread; reuse it. Frames are decoded
    /// into a caller-provided <see cref="FrameData"/>; avatar chunk arrays are validated and can then be
    /// copied with <see cref="CopyAvatarChunk"/> while the input buffer is unchanged.
    /// </summary>
    /// <summary>Rooms: the frame format of a member's stream (null: unknown member, or its avatar is incomplete).</summary>
    public interface IFrameFormatSource
    {
        FrameFormat FormatFor(string member);
    }

    public sealed partial class ServerMessageDecoder : MessageDecoderBase
    {
        /// <summary>v1 types plus the rooms messages `join` and `leave` (PROTOCOL.md 12.3, 12.4).</summary>
        public static readonly string[] Types = { "welcome", "avatar", "frame", "error", "pong", "join", "leave", "rig" };

        /// <summary>Keep each frame's arrays as they arrived in <see cref="FrameData.Payload"/> (GPU upload).</summary>
        public bool KeepPayload;
        /// <summary>Decode frames into float arrays (false with KeepPayload: validate only, FrameData.HasValues false).</summary>
        public bool DecodeValues = true;
        /// <summary>Rooms: formats of members' streams; frames carrying `member` are decoded with these. Null: v1 (member ignored).</summary>
        public IFrameFormatSource MemberFormats;

        // member ids seen so far (UTF-8 -> string), so frames allocate no strings
        readonly byte[][] _memberKeys = new byte[256][];
        readonly string[] _memberNames = new string[256];
        int _memberCount;

        // timing stage names seen so far (UTF-8 -> string), so frames allocate no strings
        readonly byte[][] _stageKeys = new byte[128][];
        readonly string[] _stageNames = new string[128];
        int _stageCount;

        // avatar chunk payload offsets, valid until the next Decode on the same buffer
        int _opOff, _shOff, _posOff, _rotOff, _sclOff;
        AvatarChunkHeader _lastChunk;
        byte[] _lastBuffer;

        /// <summary>
        /// Decodes one message into <paramref name="result"/> (its Frame is used as the frame target;
        /// one is created if null). <paramref name="format"/> is required for frames (not_ready without it).
        /// Throws <see cref="ProtocolException"/>.
        /// </summary>
        public ServerMessageKind Decode(byte[] buf, int offset, int count, FrameFormat format, ServerMessage result,
                                        int maxSize = Protocol.MaxServerMessage)
        {
            result.Kind = ServerMessageKind.None;
            Begin(buf, offset, count, maxSize);
            string t = ReadType(Types, "server");
            switch (t)
            {
                case "frame":
                    {
                        string member = GetMember(Top, "frame", false);
                        FrameFormat f = format;
                        if (MemberFormats != null) // a room session: every frame is some member's
                        {
                            if (member == null) throw Err(ErrorCodes.BadField, "a frame without 'member' in a room session");
                            f = MemberFormats.FormatFor(member);
                            if (f == null) throw Err(ErrorCodes.NotReady, "frame for member '" + member + "' before its join and complete avatar");
                        }
                        if (f == null) throw Err(ErrorCodes.NotReady, "frame before welcome: the session's format is unknown");
                        if (result.Frame == null) result.Frame = new FrameData();
                        if (f.Params) DecodeParamsFrame(result.Frame); // Rig.cs (PROTOCOL.md 13.5)
                        else if (f.Delta != null) DecodeDeltaSessionFrame(f, result.Frame); // Delta.cs (PROTOCOL.md 7.1)
                        else DecodeFrame(f, result.Frame);
                        if (!f.Params) { result.Frame.HasParams = false; result.Frame.Stamped = true; } // pooled frames
                        result.Frame.Member = member;
                        result.Kind = ServerMessageKind.Frame;
                        break;
                    }
                case "join":
                    {
                        const string w = "join";
                        JoinMessage j = new JoinMessage();
                        j.Publish = GetOptBool(Top, Keys.Publish, w) ?? true;
                        int av = GetMap(Top, Keys.Avatar, w, j.Publish); // a watch-only member has none
                        if (av >= 0 && !j.Publish) throw Err(ErrorCodes.BadField, "join: a watch-only member ('publish': false) has no 'avatar'");
                        int qm = GetMap(Top, Keys.Quant_, w, false);
                        j.Member = GetMember(Top, w, true);
                        if (av >= 0)
                        {
                            Scan(av, Sub);
                            j.AvatarId = GetStr(Sub, Keys.Id, "join.avatar", true);
                            j.Count = (int)Math.Min(int.MaxValue, GetInt(Sub, Keys.Count, "join.avatar", 0, Protocol.UInt32Max));
                            j.ShDegree = (int)GetInt(Sub, Keys.ShDegree, "join.avatar", 0, Protocol.MaxShDegree);
                        }
                        if (qm >= 0) j.Quant = DecodeQuant(qm);
                        result.Join = j;
                        result.Kind = ServerMessageKind.Join;
                        break;
                    }
                case "leave":
                    {
                        LeaveMessage l = new LeaveMessage();
                        l.Member = GetMember(Top, "leave", true);
                        l.Reason = GetStr(Top, Keys.Reason, "leave", false, Protocol.MaxStringBytes, 0);
                        result.Leave = l;
                        result.Kind = ServerMessageKind.Leave;
                        break;
                    }
                case "rig": // Rig.cs (PROTOCOL.md 13.2)
                    result.Rig = DecodeRigChunk();
                    result.Kind = ServerMessageKind.Rig;
                    break;
                case "avatar":
                    result.Avatar = DecodeAvatarChunk();
                    _lastBuffer = buf;
                    result.Kind = ServerMessageKind.Avatar;
                    break;
                case "welcome":
                    result.Welcome = DecodeWelcome();
                    result.Kind = ServerMessageKind.Welcome;
                    break;
                case "error":
                    {
                        const string w = "error";
                        ErrorMessage e = new ErrorMessage();
                        e.Code = GetStr(Top, Keys.Code, w, true);
                        e.Message = GetStr(Top, Keys.Message, w, true, Protocol.MaxStringBytes, 0);
                        e.Fatal = GetBool(Top, Keys.Fatal, w);
                        e.Seq = GetOptInt(Top, Keys.Seq, w, 0, long.MaxValue);
                        result.Error = e;
                        result.Kind = ServerMessageKind.Error;
                        break;
                    }
                default: // pong
                    result.PongT = GetInt(Top, Keys.T, "pong", long.MinValue, long.MaxValue);
                    result.Kind = ServerMessageKind.Pong;
                    break;
            }
            return result.Kind;
        }

        Welcome DecodeWelcome()
        {
            const string w = "welcome";
            Welcome m = new Welcome();
            long protocol = GetInt(Top, Keys.Protocol_, w, long.MinValue, long.MaxValue);
            if (protocol != Protocol.Version)
                throw Err(ErrorCodes.UnsupportedProtocol, "server speaks protocol " + protocol + "; this client speaks " + Protocol.Version);
            m.Protocol = (int)protocol;
            m.Room = GetStr(Top, Keys.Room, w, false, Protocol.MaxRoomLength); // rooms (PROTOCOL.md 12.2)
            int av = GetMap(Top, Keys.Avatar, w, m.Room == null); // a watch-only room session has none
            if (av >= 0)
            {
                Scan(av, Sub);
                m.AvatarId = GetStr(Sub, Keys.Id, "welcome.avatar", true);
                m.Count = (int)Math.Min(int.MaxValue, GetInt(Sub, Keys.Count, "welcome.avatar", 0, Protocol.UInt32Max));
                m.ShDegree = (int)GetInt(Sub, Keys.ShDegree, "welcome.avatar", 0, Protocol.MaxShDegree);
            }
            m.Encoding = GetChoice(Top, Keys.Encoding_, w, ParamsProtocol.HelloEncodings, ErrorCodes.UnknownEncoding, null);
            int qm = GetMap(Top, Keys.Quant_, w, m.Encoding == "q13" && m.Room == null); // rooms: each join has its own
            m.Session = GetStr(Top, Keys.Session, w, true);
            m.Layout = GetChoice(Top, Keys.Layout, w, Protocol.Layouts, ErrorCodes.UnknownLayout, null);
            m.Coords = GetChoice(Top, Keys.Coords, w, Protocol.CoordsNames, ErrorCodes.BadField, null);
            m.Sparse = GetBool(Top, Keys.Sparse, w);
            m.Delta = GetOptBool(Top, Keys.Delta, w) ?? false;
            if (qm >= 0 && m.Encoding == "q13") m.Quant = DecodeQuant(qm);
            m.Server = GetStr(Top, Keys.Server, w, false);
            m.RigBytes = GetOptInt(Top, Keys.RigBytes, w, 0, Protocol.UInt32Max);
            m.Member = GetMember(Top, w, m.Room != null);
            return m;
        }

        /// <summary>
        /// A `member` id: a string of 1..256 characters (PROTOCOL.md 12.2). Interned: a known id allocates nothing.
        /// </summary>
        internal string GetMember(int[] s, string where, bool required)
        {
            if (s[Keys.Member] < 0)
            {
                if (required) throw Err(ErrorCodes.BadField, where + ": missing field 'member'");
                return null;
            }
            R.Position = s[Keys.Member];
            MsgType t = R.PeekType();
            if (t != MsgType.Str) throw Err(ErrorCodes.BadField, where + ": field 'member' must be a str, got " + R.PeekTypeName());
            int off, len;
            R.ReadStringSegment(out off, out len);
            int cp = CodePoints(R.Buffer, off, len);
            if (cp < 1 || cp > Protocol.MaxIdLength) throw Err(ErrorCodes.BadField, where + ": field 'member' must have 1.." + Protocol.MaxIdLength + " characters, got " + cp);
            byte[] b = R.Buffer;
            for (int i = 0; i < _memberCount; i++)
            {
                byte[] k = _memberKeys[i];
                if (k.Length != len) continue;
                int j = 0;
                while (j < len && b[off + j] == k[j]) j++;
                if (j == len) return _memberNames[i];
            }
            byte[] copy = new byte[len];
            Buffer.BlockCopy(b, off, copy, 0, len);
            return Intern(copy, System.Text.Encoding.UTF8.GetString(b, off, len));
        }

        string Intern(byte[] key, string name)
        {
            if (_memberCount == _memberKeys.Length) _memberCount = 0; // a long-lived room: start over (rare)
            _memberKeys[_memberCount] = key;
            _memberNames[_memberCount] = name;
            _memberCount++;
            return name;
        }

        Quant DecodeQuant(int pos)
        {
            const string w = "welcome.quant";
            Scan(pos, Sub);
            Quant q = new Quant();
            int off;
            GetArray(Sub, Keys.PosMin, w, 4, 3, true, out off, "float32");
            CheckFiniteF32(off, 3, w, Keys.PosMin);
            for (int i = 0; i < 3; i++) q.PosMin[i] = BitCast.ReadFloatLE(R.Buffer, off + 4 * i);
            GetArray(Sub, Keys.PosMax, w, 4, 3, true, out off, "float32");
            CheckFiniteF32(off, 3, w, Keys.PosMax);
            for (int i = 0; i < 3; i++) q.PosMax[i] = BitCast.ReadFloatLE(R.Buffer, off + 4 * i);
            GetArray(Sub, Keys.LogScale, w, 4, 2, true, out off, "float32");
            CheckFiniteF32(off, 2, w, Keys.LogScale);
            for (int i = 0; i < 2; i++) q.LogScale[i] = BitCast.ReadFloatLE(R.Buffer, off + 4 * i);
            for (int i = 0; i < 3; i++)
                if (!(q.PosMax[i] > q.PosMin[i])) throw Err(ErrorCodes.BadField, w + ": quant.pos_max must exceed quant.pos_min on every axis");
            if (!(q.LogScale[1] > q.LogScale[0])) throw Err(ErrorCodes.BadField, w + ": quant.log_scale must be [min, max] with max > min");
            return q;
        }

        AvatarChunkHeader DecodeAvatarChunk()
        {
            const string w = "avatar";
            AvatarChunkHeader h = new AvatarChunkHeader();
            long count = GetInt(Top, Keys.Count, w, 0, Protocol.UInt32Max);
            int deg = (int)GetInt(Top, Keys.ShDegree, w, 0, Protocol.MaxShDegree);
            long chunks = GetInt(Top, Keys.Chunks, w, 1, Protocol.UInt32Max);
            long chunk = GetInt(Top, Keys.Chunk, w, 0, chunks - 1);
            long offset = GetInt(Top, Keys.Offset, w, 0, count);
            long n = GetInt(Top, Keys.N, w, 0, count - offset);
            int k = Protocol.ShCoefficients(deg);
            GetArray(Top, Keys.Opacity, w, 4, n, true, out _opOff, "float32");
            CheckFiniteF32(_opOff, n, w, Keys.Opacity);
            for (long i = 0; i < n; i++)
            {
                float o = BitCast.ReadFloatLE(R.Buffer, (int)(_opOff + 4 * i));
                if (!(o >= 0f && o <= 1f)) throw Err(ErrorCodes.BadField, "avatar: field 'opacity' has values outside [0, 1]");
            }
            GetArray(Top, Keys.Sh, w, 4, n * k * 3, true, out _shOff, "float32");
            CheckFiniteF32(_shOff, n * k * 3, w, Keys.Sh);
            GetArray(Top, Keys.Position, w, 4, n * 3, true, out _posOff, "float32");
            CheckFiniteF32(_posOff, n * 3, w, Keys.Position);
            GetArray(Top, Keys.Rotation, w, 4, n * 4, true, out _rotOff, "float32");
            CheckFiniteF32(_rotOff, n * 4, w, Keys.Rotation);
            GetArray(Top, Keys.Scale, w, 4, n * 3, true, out _sclOff, "float32");
            CheckFiniteF32(_sclOff, n * 3, w, Keys.Scale);
            if (count > int.MaxValue) throw Err(ErrorCodes.BadField, "avatar: count " + count + " is too large for this client");
            h.Member = GetMember(Top, w, false);
            h.Count = (int)count; h.ShDegree = deg; h.Chunk = (int)chunk; h.Chunks = (int)Math.Min(chunks, int.MaxValue);
            h.Offset = (int)offset; h.N = (int)n;
            _lastChunk = h;
            return h;
        }

        /// <summary>
        /// Copies the arrays of the avatar chunk just decoded from <paramref name="buf"/> into
        /// <paramref name="target"/> at the chunk's offset. Call before the buffer is reused.
        /// </summary>
        public void CopyAvatarChunk(byte[] buf, AvatarData target)
        {
            if (!ReferenceEquals(buf, _lastBuffer)) throw new InvalidOperationException("CopyAvatarChunk needs the buffer of the last decoded avatar chunk");
            AvatarChunkHeader h = _lastChunk;
            if (h.Count != target.Count || h.ShDegree != target.ShDegree || h.Offset + h.N > target.Count)
                throw new InvalidOperationException("avatar chunk does not fit the target");
            int n = h.N, k = target.K;
            FrameCodec.DecodeF32(buf, _opOff, n, target.Opacity, h.Offset);
            FrameCodec.DecodeF32(buf, _shOff, n * k * 3, target.Sh, h.Offset * k * 3);
            FrameCodec.DecodeF32(buf, _posOff, n * 3, target.Position, h.Offset * 3);
            FrameCodec.DecodeF32(buf, _rotOff, n * 4, target.Rotation, h.Offset * 4);
            FrameCodec.DecodeF32(buf, _sclOff, n * 3, target.Scale, h.Offset * 3);
        }

        void DecodeTiming(FrameData f)
        {
            const string w = "frame";
            int pos = GetMap(Top, Keys.Timing, w, true);
            R.Position = pos;
            int n = R.ReadMapHeader();
            if (n > Protocol.MaxTimingStages)
                throw Err(ErrorCodes.BadField, "frame: 'timing' has " + n + " stages, at most " + Protocol.MaxTimingStages);
            int stored = 0;
            for (int i = 0; i < n; i++)
            {
                int ko, kl;
                R.ReadStringSegment(out ko, out kl);
                if (CodePoints(R.Buffer, ko, kl) > Protocol.MaxIdLength)
                    throw Err(ErrorCodes.BadField, "frame: timing stage name longer than " + Protocol.MaxIdLength);
                string name = StageName(ko, kl);
                if (R.PeekType() == MsgType.Nil) // nil is "missing" in the reference decoder
                    throw Err(ErrorCodes.BadField, "frame.timing: missing field '" + name + "'");
                if (R.PeekType() != MsgType.Int)
                    throw Err(ErrorCodes.BadField, "frame.timing: field '" + name + "' must be an int, got " + R.PeekTypeName());
                bool overflow;
                long v = R.ReadInteger(out overflow);
                if (overflow || v < 0)
                    throw Err(ErrorCodes.BadField, "frame.timing: field '" + name + "' = " + v + " is outside [0, " + long.MaxValue + "]");
                int slot = -1;
                for (int j = 0; j < stored; j++) if (f.TimingNames[j] == name) { slot = j; break; }
                if (slot < 0) slot = stored++;
                f.TimingNames[slot] = name;
                f.TimingValues[slot] = v;
            }
            f.TimingCount = stored;
        }

        string StageName(int off, int len)
        {
            byte[] b = R.Buffer;
            for (int i = 0; i < _stageCount; i++)
            {
                byte[] key = _stageKeys[i];
                if (key.Length != len) continue;
                int j = 0;
                while (j < len && b[off + j] == key[j]) j++;
                if (j == len) return _stageNames[i];
            }
            string s = System.Text.Encoding.UTF8.GetString(b, off, len);
            if (_stageCount < _stageKeys.Length)
            {
                byte[] copy = new byte[len];
                Buffer.BlockCopy(b, off, copy, 0, len);
                _stageKeys[_stageCount] = copy;
                _stageNames[_stageCount] = s;
                _stageCount++;
            }
            return s;
        }

        void DecodeFrame(FrameFormat fmt, FrameData f)
        {
            const string w = "frame";
            f.Seq = GetInt(Top, Keys.Seq, w, 0, long.MaxValue);
            f.T = GetInt(Top, Keys.T, w, long.MinValue, long.MaxValue);
            DecodeTiming(f);
            long n = GetInt(Top, Keys.N, w, 0, Protocol.UInt32Max);
            int idxOff;
            bool hasIndex = GetArray(Top, Keys.Index, w, 4, n, false, out idxOff, "uint32");
            byte[] b = R.Buffer;
            if (!hasIndex)
            {
                if (n != fmt.Count)
                    throw Err(ErrorCodes.BadLength, "frame: dense frame carries n=" + n + " Gaussians, the avatar has " + fmt.Count);
            }
            else
            {
                if (!fmt.Sparse) throw Err(ErrorCodes.BadField, "frame: 'index' in a session that did not ask for sparse frames");
                if (n > 0)
                {
                    uint last = BitCast.ReadUInt32LE(b, (int)(idxOff + 4 * (n - 1)));
                    if (last >= (uint)fmt.Count) throw Err(ErrorCodes.BadField, "frame: index " + last + " >= avatar count " + fmt.Count);
                }
                uint prev = 0;
                for (long i = 0; i < n; i++)
                {
                    uint v = BitCast.ReadUInt32LE(b, (int)(idxOff + 4 * i));
                    if (i > 0 && v <= prev) throw Err(ErrorCodes.BadField, "frame: 'index' must be strictly ascending");
                    prev = v;
                }
            }
            int pOff, pLen, rOff, rLen, sOff, sLen;
            GetBin(Top, Keys.Position, w, true, out pOff, out pLen);
            GetBin(Top, Keys.Rotation, w, true, out rOff, out rLen);
            GetBin(Top, Keys.Scale, w, true, out sOff, out sLen);
            int pb, rb, sb;
            Protocol.FieldBytes(fmt.Encoding, out pb, out rb, out sb);
            string enc = Protocol.EncodingName(fmt.Encoding);
            CheckLength("position", pLen, n, pb, enc);
            CheckLength("rotation", rLen, n, rb, enc);
            CheckLength("scale", sLen, n, sb, enc);

            int ni = (int)n; // bounded by the message size through the length checks above
            f.EnsureCapacity(ni);
            f.N = ni;
            f.HasIndex = hasIndex;
            if (hasIndex)
            {
                if (BitConverter.IsLittleEndian) Buffer.BlockCopy(b, idxOff, f.Index, 0, 4 * ni);
                else for (int i = 0; i < ni; i++) f.Index[i] = BitCast.ReadUInt32LE(b, idxOff + 4 * i);
            }
            f.HasValues = DecodeValues || !KeepPayload;
            if (!f.HasValues)
            {
                // validate as the float decoders do, without decoding
                if (fmt.Encoding == FrameEncoding.F32)
                {
                    CheckFiniteF32(pOff, 3L * ni, w, Keys.Position);
                    CheckFiniteF32(rOff, 4L * ni, w, Keys.Rotation);
                    CheckFiniteF32(sOff, 3L * ni, w, Keys.Scale);
                }
                else if (fmt.Encoding == FrameEncoding.F16)
                {
                    if (!FiniteF16(b, pOff, 3 * ni)) throw NonFinite("position");
                    if (!FiniteF16(b, rOff, 4 * ni)) throw NonFinite("rotation");
                    if (!FiniteF16(b, sOff, 3 * ni)) throw NonFinite("scale");
                }
                f.Payload.Fill(b, fmt.Encoding, ni, hasIndex, idxOff, pOff, pLen, rOff, rLen, sOff, sLen);
                return;
            }
            if (KeepPayload) f.Payload.Fill(b, fmt.Encoding, ni, hasIndex, idxOff, pOff, pLen, rOff, rLen, sOff, sLen);
            else f.Payload.Length = 0;
            switch (fmt.Encoding)
            {
                case FrameEncoding.Q13:
                    FrameCodec.DecodeQ13Positions(b, pOff, ni, fmt.Quant, f.Position, 0);
                    FrameCodec.DecodeQ13Rotations(b, rOff, ni, f.Rotation, 0);
                    FrameCodec.DecodeQ13Scales(b, sOff, ni, fmt.Quant, f.Scale, 0);
                    break;
                case FrameEncoding.F16:
                    if (!FrameCodec.DecodeF16(b, pOff, 3 * ni, f.Position, 0)) throw NonFinite("position");
                    if (!FrameCodec.DecodeF16(b, rOff, 4 * ni, f.Rotation, 0)) throw NonFinite("rotation");
                    if (!FrameCodec.DecodeF16(b, sOff, 3 * ni, f.Scale, 0)) throw NonFinite("scale");
                    break;
                default:
                    if (!FrameCodec.DecodeF32(b, pOff, 3 * ni, f.Position, 0)) throw NonFinite("position");
                    if (!FrameCodec.DecodeF32(b, rOff, 4 * ni, f.Rotation, 0)) throw NonFinite("rotation");
                    if (!FrameCodec.DecodeF32(b, sOff, 3 * ni, f.Scale, 0)) throw NonFinite("scale");
                    break;
            }
        }

        static bool FiniteF16(byte[] b, int off, int count)
        {
            for (int i = 0; i < count; i++)
                if ((b[off + 2 * i + 1] & 0x7c) == 0x7c) return false;
            return true;
        }

        static ProtocolException NonFinite(string field)
        {
            return Err(ErrorCodes.NonFinite, "frame field '" + field + "' holds NaN or infinity");
        }

        static void CheckLength(string name, int len, long n, int size, string enc)
        {
            if (len != n * size)
                throw Err(ErrorCodes.BadLength, "frame field '" + name + "' has " + len + " bytes; " + n + " Gaussians in " + enc + " need " + (n * size));
        }
    }

    /// <summary>Decodes client -> server messages (what a server does); used by tests and tools.</summary>
    public sealed class ClientMessageDecoder : MessageDecoderBase
    {
        public static readonly string[] Types = { "hello", "bs", "ping", "bye", "resync" };

        /// <summary><paramref name="layout"/>: the session's layout, fixing the length of bs.w (null: any known length).</summary>
        public ClientMessageKind Decode(byte[] buf, int offset, int count, string layout, ClientMessage result,
                                        int maxSize = Protocol.MaxClientMessage)
        {
            result.Kind = ClientMessageKind.None;
            Begin(buf, offset, count, maxSize);
            string t = ReadType(Types, "client");
            switch (t)
            {
                case "bs": DecodeBs(layout, result.Blendshapes); result.Kind = ClientMessageKind.Blendshapes; break;
                case "hello": result.Hello = DecodeHello(); result.Kind = ClientMessageKind.Hello; break;
                case "ping": result.PingT = GetInt(Top, Keys.T, "ping", long.MinValue, long.MaxValue); result.Kind = ClientMessageKind.Ping; break;
                case "resync": result.Kind = ClientMessageKind.Resync; break;
                default: result.Kind = ClientMessageKind.Bye; break;
            }
            return result.Kind;
        }

        Hello DecodeHello()
        {
            const string w = "hello";
            long protocol = GetInt(Top, Keys.Protocol_, w, long.MinValue, long.MaxValue);
            if (protocol != Protocol.Version)
                throw Err(ErrorCodes.UnsupportedProtocol, "protocol " + protocol + " is not supported; this server speaks protocol " + Protocol.Version);
            Hello h = new Hello();
            h.Protocol = (int)protocol;
            h.Room = GetStr(Top, Keys.Room, w, false, Protocol.MaxRoomLength); // rooms (PROTOCOL.md 12)
            if (h.Room != null && !Protocol.IsRoomName(h.Room))
                throw Err(ErrorCodes.BadField, "hello: field 'room' '" + h.Room + "' may hold only letters, digits and . _ -");
            bool publish = GetOptBool(Top, Keys.Publish, w) ?? true;
            if (h.Room != null && publish && Top[Keys.Avatar] < 0)
                throw Err(ErrorCodes.BadField, "hello: field 'avatar' is required to publish in a room (or send 'publish': false to watch)");
            if (h.Room != null)
            {
                h.Publish = publish;
                h.Self = GetOptBool(Top, Keys.Self, w) ?? false;
                h.RoomToken = GetStr(Top, Keys.RoomToken, w, false);
            }
            bool watching = h.Room != null && !publish; // a watcher sends no bs: its layout is optional
            h.Layout = GetChoice(Top, Keys.Layout, w, Protocol.Layouts, ErrorCodes.UnknownLayout, watching ? "arkit52" : null);
            h.Avatar = GetStr(Top, Keys.Avatar, w, false) ?? "default";
            h.Encoding = GetChoice(Top, Keys.Encoding_, w, ParamsProtocol.HelloEncodings, ErrorCodes.UnknownEncoding, "f32");
            h.Coords = GetChoice(Top, Keys.Coords, w, Protocol.CoordsNames, ErrorCodes.BadField, "flame");
            bool? sparse = GetOptBool(Top, Keys.Sparse, w);
            h.Sparse = sparse ?? false;
            h.Delta = GetOptBool(Top, Keys.Delta, w) ?? false;
            h.Device = GetStr(Top, Keys.Device, w, false);
            h.Token = GetStr(Top, Keys.Token, w, false, Protocol.MaxStringBytes);
            h.MaxGaussians = GetOptInt(Top, Keys.MaxGaussians, w, 1, Protocol.UInt32Max);
            return h;
        }

        void DecodeBs(string layout, Blendshapes bs)
        {
            const string w = "bs";
            bs.Seq = GetInt(Top, Keys.Seq, w, 0, long.MaxValue);
            bs.T = GetInt(Top, Keys.T, w, long.MinValue, long.MaxValue);
            int off, len;
            GetBin(Top, Keys.W, w, true, out off, out len);
            int n;
            if (layout != null) n = Protocol.LayoutLength(layout);
            else if (len % 4 == 0 && len >= 4 && len <= 4 * 70) n = len / 4;
            else throw Err(ErrorCodes.BadLength, "bs: field 'w' has " + len + " bytes, not a whole number of float32 weights of a known layout");
            if (len != 4 * n)
                throw Err(ErrorCodes.BadLength, "bs: field 'w' has " + len + " bytes; layout " + layout + " needs " + n + " float32 = " + (4 * n) + " bytes");
            CheckFiniteF32(off, n, w, Keys.W);
            if (bs.W.Length < n) bs.W = new float[n];
            FrameCodec.DecodeF32(R.Buffer, off, n, bs.W, 0);
            bs.Count = n;
        }
    }

    /// <summary>Encoders of client -> server messages into a reusable writer (byte-identical to the Python reference).</summary>
    public static class ClientMessageEncoder
    {
        public static void Hello(MsgPackWriter w, Hello h)
        {
            int n = 3;
            if (h.Avatar != null) n++;
            if (h.Encoding != null) n++;
            if (h.Coords != null) n++;
            if (h.Sparse.HasValue) n++;
            if (h.Delta == true) n++;
            if (h.Device != null) n++;
            if (h.Token != null) n++;
            if (h.MaxGaussians.HasValue) n++;
            // rooms: publish is written only when false, self only when true, as the reference does
            bool room = h.Room != null, watch = room && h.Publish == false, self = room && h.Self == true;
            if (room) n++;
            if (watch) n++;
            if (self) n++;
            if (room && h.RoomToken != null) n++;
            w.WriteMapHeader(n);
            w.WriteString("type"); w.WriteString("hello");
            w.WriteString("protocol"); w.WriteInt(h.Protocol);
            w.WriteString("layout"); w.WriteString(h.Layout);
            if (h.Avatar != null) { w.WriteString("avatar"); w.WriteString(h.Avatar); }
            if (h.Encoding != null) { w.WriteString("encoding"); w.WriteString(h.Encoding); }
            if (h.Coords != null) { w.WriteString("coords"); w.WriteString(h.Coords); }
            if (h.Sparse.HasValue) { w.WriteString("sparse"); w.WriteBool(h.Sparse.Value); }
            if (h.Delta == true) { w.WriteString("delta"); w.WriteBool(true); }
            if (h.Device != null) { w.WriteString("device"); w.WriteString(h.Device); }
            if (h.Token != null) { w.WriteString("token"); w.WriteString(h.Token); }
            if (h.MaxGaussians.HasValue) { w.WriteString("max_gaussians"); w.WriteInt(h.MaxGaussians.Value); }
            if (room) { w.WriteString("room"); w.WriteString(h.Room); }
            if (watch) { w.WriteString("publish"); w.WriteBool(false); }
            if (self) { w.WriteString("self"); w.WriteBool(true); }
            if (room && h.RoomToken != null) { w.WriteString("room_token"); w.WriteString(h.RoomToken); }
        }

        static readonly byte[] BsPrefix = { 0x84, 0xa4, (byte)'t', (byte)'y', (byte)'p', (byte)'e', 0xa2, (byte)'b', (byte)'s', 0xa3, (byte)'s', (byte)'e', (byte)'q' };
        static readonly byte[] TKey = { 0xa1, (byte)'t' };
        static readonly byte[] WKey = { 0xa1, (byte)'w' };

        /// <summary>`bs` with <paramref name="count"/> weights from <paramref name="weights"/> (allocation-free).</summary>
        public static void Bs(MsgPackWriter w, long seq, long t, float[] weights, int count)
        {
            w.WriteRaw(BsPrefix, 0, BsPrefix.Length);
            w.WriteInt(seq);
            w.WriteRaw(TKey, 0, 2);
            w.WriteInt(t);
            w.WriteRaw(WKey, 0, 2);
            w.WriteFloat32Bin(weights, 0, count);
        }

        public static void Ping(MsgPackWriter w, long t)
        {
            w.WriteMapHeader(2);
            w.WriteString("type"); w.WriteString("ping");
            w.WriteString("t"); w.WriteInt(t);
        }

        public static void Bye(MsgPackWriter w)
        {
            w.WriteMapHeader(1);
            w.WriteString("type"); w.WriteString("bye");
        }

        /// <summary>`resync`: a delta-session client asks for a key frame (PROTOCOL.md 7.1).</summary>
        public static void Resync(MsgPackWriter w)
        {
            w.WriteMapHeader(1);
            w.WriteString("type"); w.WriteString("resync");
        }
    }
}
