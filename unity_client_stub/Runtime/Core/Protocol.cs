// OFERA streaming protocol v1: constants, error codes and the protocol exception.
// UnityEngine-free (compiled under mono by Tests/run.sh). C# 7.2 at most.
using System;

namespace Ofera.Client
{
    /// <summary>Constants of protocol v1 (see protocol/PROTOCOL.md).</summary>
    public static class Protocol
    {
        public const int Version = 1;
        public const string Endpoint = "/v1/stream";

        /// <summary>Largest client -> server message (64 KiB).</summary>
        public const int MaxClientMessage = 64 * 1024;
        /// <summary>Largest server -> client message (64 MiB); a client must accept up to this.</summary>
        public const int MaxServerMessage = 64 * 1024 * 1024;
        public const int MaxDepth = 4;
        public const int MaxContainerLength = 256;
        public const int MaxStringBytes = 4096;
        public const int MaxIdLength = 256;
        public const int MaxTimingStages = 64;
        public const int MaxShDegree = 3;
        public const long UInt32Max = 4294967295L;
        /// <summary>Longest room name (PROTOCOL.md 12.1).</summary>
        public const int MaxRoomLength = 64;

        public static readonly string[] Layouts = { "arkit52", "arkit51", "mediapipe52", "ovr63", "ovr70", "livelink61" };
        public static readonly string[] Encodings = { "f32", "f16", "q13" };
        public static readonly string[] CoordsNames = { "flame", "unity" };

        /// <summary>Number of float32 weights of a layout, or -1 if unknown.</summary>
        public static int LayoutLength(string layout)
        {
            switch (layout)
            {
                case "arkit52": return 52;
                case "arkit51": return 51;
                case "mediapipe52": return 52;
                case "ovr63": return 63;
                case "ovr70": return 70;
                case "livelink61": return 61;
                default: return -1;
            }
        }

        /// <summary>Frame payload bytes per Gaussian (position, rotation, scale) of an encoding.</summary>
        public static void FieldBytes(FrameEncoding e, out int position, out int rotation, out int scale)
        {
            switch (e)
            {
                case FrameEncoding.F16: position = 6; rotation = 8; scale = 6; return;
                case FrameEncoding.Q13: position = 6; rotation = 4; scale = 3; return;
                default: position = 12; rotation = 16; scale = 12; return;
            }
        }

        public static bool TryParseEncoding(string s, out FrameEncoding e)
        {
            switch (s)
            {
                case "f32": e = FrameEncoding.F32; return true;
                case "f16": e = FrameEncoding.F16; return true;
                case "q13": e = FrameEncoding.Q13; return true;
                default: e = FrameEncoding.F32; return false;
            }
        }

        public static string EncodingName(FrameEncoding e)
        {
            switch (e)
            {
                case FrameEncoding.F16: return "f16";
                case FrameEncoding.Q13: return "q13";
                default: return "f32";
            }
        }

        /// <summary>Number of SH coefficients per colour channel: (degree + 1)^2.</summary>
        public static int ShCoefficients(int shDegree) { return (shDegree + 1) * (shDegree + 1); }

        /// <summary>A room name: 1 to 64 of A-Z a-z 0-9 . _ - (PROTOCOL.md 12.1).</summary>
        public static bool IsRoomName(string room)
        {
            if (string.IsNullOrEmpty(room) || room.Length > MaxRoomLength) return false;
            foreach (char c in room)
                if (!((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' || c == '-')) return false;
            return true;
        }

        internal static bool Contains(string[] set, string v)
        {
            for (int i = 0; i < set.Length; i++) if (set[i] == v) return true;
            return false;
        }
    }

    public enum FrameEncoding { F32 = 0, F16 = 1, Q13 = 2 }

    /// <summary>Stable error codes of protocol v1 and their WebSocket close codes.</summary>
    public static class ErrorCodes
    {
        public const string Malformed = "malformed";
        public const string UnknownType = "unknown_type";
        public const string BadField = "bad_field";
        public const string BadLength = "bad_length";
        public const string NonFinite = "non_finite";
        public const string NotReady = "not_ready";
        public const string DuplicateHello = "duplicate_hello";
        public const string UnsupportedProtocol = "unsupported_protocol";
        public const string UnknownLayout = "unknown_layout";
        public const string UnknownAvatar = "unknown_avatar";
        public const string UnknownEncoding = "unknown_encoding";
        public const string Unauthorized = "unauthorized";
        public const string MessageTooLarge = "message_too_large";
        public const string RateLimited = "rate_limited";
        public const string ServerFull = "server_full";
        public const string TextFrame = "text_frame";
        public const string Internal = "internal";
        /// <summary>Rooms (PROTOCOL.md 12.6): the room has its most members / the server its most rooms (try again later).</summary>
        public const string RoomFull = "room_full";
        public const string TooManyRooms = "too_many_rooms";

        /// <summary>True for codes that are fatal whenever they occur.</summary>
        public static bool AlwaysFatal(string code)
        {
            switch (code)
            {
                case UnsupportedProtocol: case UnknownLayout: case UnknownAvatar: case UnknownEncoding:
                case Unauthorized: case MessageTooLarge: case ServerFull: case TextFrame: case Internal:
                case RoomFull: case TooManyRooms:
                    return true;
                default:
                    return false;
            }
        }

        /// <summary>WebSocket close code after a fatal error (4000 for codes unknown to v1).</summary>
        public static int CloseCode(string code)
        {
            switch (code)
            {
                case Malformed: return 4000;
                case UnknownType: return 4001;
                case BadField: return 4002;
                case BadLength: return 4003;
                case NonFinite: return 4004;
                case NotReady: return 4005;
                case UnsupportedProtocol: return 4010;
                case UnknownLayout: return 4011;
                case UnknownAvatar: return 4012;
                case UnknownEncoding: return 4013;
                case Unauthorized: return 1008;
                case MessageTooLarge: return 1009;
                case ServerFull: return 1013;
                case TextFrame: return 1003;
                case Internal: return 1011;
                case RoomFull: return 4014;
                case TooManyRooms: return 4015;
                default: return 4000;
            }
        }

        /// <summary>Fatal errors that a reconnect cannot fix (the configuration is wrong): stop retrying.</summary>
        public static bool IsConfigurationError(string code)
        {
            switch (code)
            {
                case UnsupportedProtocol: case UnknownLayout: case UnknownAvatar: case UnknownEncoding:
                case Unauthorized:
                    return true;
                default:
                    return false;
            }
        }
    }

    /// <summary>A received message violated the protocol: wire error code, human message, fatality.</summary>
    public sealed class ProtocolException : Exception
    {
        public readonly string Code;
        public readonly bool Fatal;

        public ProtocolException(string code, string message) : this(code, message, ErrorCodes.AlwaysFatal(code)) { }

        public ProtocolException(string code, string message, bool fatal) : base(code + ": " + message)
        {
            Code = code;
            Fatal = fatal;
            Detail = message;
        }

        /// <summary>The message without the code prefix.</summary>
        public readonly string Detail;

        public int CloseCode { get { return ErrorCodes.CloseCode(Code); } }

        public ProtocolException AsFatal() { return Fatal ? this : new ProtocolException(Code, Detail, true); }
    }
}
