// Expression streaming (PROTOCOL.md 13, "params" encoding): the rig a params-session client deforms the avatar
// with. RigAssembler puts the `rig` chunks back together; RigDecoder checks and decodes the rig body (one msgpack
// map) into RigData, mirroring ofera_protocol/rig.py's decode_rig (same checks, same codes); RigData also keeps
// the body's arrays as GPU words (RigData.Gpu), the layout OferaRigDeform.compute reads. UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    /// <summary>Constants of params sessions.</summary>
    public static class ParamsProtocol
    {
        /// <summary>`hello.encoding` / `welcome.encoding` of a params session.</summary>
        public const string Encoding = "params";
        /// <summary>Every encoding a hello or welcome may name: the frame encodings, then params.</summary>
        public static readonly string[] HelloEncodings = { "f32", "f16", "q13", Encoding };
        /// <summary>Float32 values of a params frame: 50 expression values, then jaw, left eye, right eye as 6D.</summary>
        public const int Length = 68;
        public const int ExprValues = 50;
        /// <summary>FLAME's joints: root, neck, jaw, left eye, right eye.</summary>
        public const int Joints = 5;
        /// <summary>Entries of FLAME's pose feature (R_k - I of joints 1..4, row-major).</summary>
        public const int PoseFeature = 9 * (Joints - 1);
        /// <summary>Largest rig body a client accepts (64 MiB).</summary>
        public const int MaxRigBytes = Protocol.MaxServerMessage;
    }

    public enum RigBinding { Triangle, Barycentric }

    /// <summary>
    /// One avatar's rig, FLAME space, metres (ofera_protocol.rig.Rig): S vertices, U faces, M Gaussians, E expression
    /// components, P pose-corrective rows. Arrays are row-major, float32 (the f16 wire arrays pose_basis, local_rotation
    /// and local_scale converted exactly).
    /// </summary>
    public sealed class RigData
    {
        public RigBinding Binding;
        /// <summary>Gaussians of the session's avatar (N).</summary>
        public int Count;
        public int Vertices, Faces, Gaussians, ExprDims, PoseCount;
        /// <summary>M session ids (strictly ascending) of the Gaussians the rig deforms.</summary>
        public uint[] Index;
        /// <summary>5 x 3 joints and 5 x 3 x E their motion per expression coefficient.</summary>
        public float[] Joints, JointsExpr;
        /// <summary>S x 3 template (identity baked in); S x E x 3 expression basis; S x P x 3 pose basis; S x 5 weights.</summary>
        public float[] Template, ExprBasis, PoseBasis, Weights;
        /// <summary>P entries of the 36-long pose feature, ascending.</summary>
        public byte[] PoseRows;
        /// <summary>U x 3 rig vertex rows; M rig face rows.</summary>
        public int[] Face, GaussianFace;
        /// <summary>M x 3: triangle local position (face units) or barycentric coordinates.</summary>
        public float[] Local;
        /// <summary>Barycentric only: M offsets along the unnormalised normal (null for triangle rigs).</summary>
        public float[] NormalOffset;
        /// <summary>M x 4 (x, y, z, w) and M x 3 (the scale is LocalScale * s_f).</summary>
        public float[] LocalRotation, LocalScale;
        /// <summary>The body's arrays as 32-bit words for the GPU (uploaded as they arrived).</summary>
        public RigGpuWords Gpu;
    }

    /// <summary>
    /// The rig body's arrays as GPU words, in wire order, each section copied byte for byte from its bin and starting
    /// on a 4-byte boundary (zero padding): index u32, joints f32, joints_expr f32, template f32, expr_basis f32,
    /// pose_rows u8, pose_basis f16, weights f32, face u32, gaussian_face u32, local_position or bary f32,
    /// normal_offset f32 (empty for triangle rigs), local_rotation f16, local_scale f16.
    /// <see cref="Word"/> holds each section's first word (OferaRigDeform.compute's _OferaRig*Word).
    /// </summary>
    public sealed class RigGpuWords
    {
        public const int Index = 0, Joints = 1, JointsExpr = 2, Template = 3, ExprBasis = 4, PoseRows = 5, PoseBasis = 6,
            Weights = 7, Face = 8, GaussianFace = 9, Local = 10, NormalOffset = 11, LocalRotation = 12, LocalScale = 13;
        public const int Sections = 14;
        public uint[] Words;
        public readonly int[] Word = new int[Sections];
    }

    /// <summary>Collects the `rig` chunks of one avatar, which must arrive in order without gaps (ofera_protocol.rig.RigAssembler).</summary>
    public sealed class RigAssembler
    {
        byte[] _body;
        int _next, _size = -1, _chunks = -1, _received;

        public bool Complete { get { return _chunks >= 0 && _received == _chunks; } }
        /// <summary>The whole body (only once Complete).</summary>
        public byte[] Body { get { if (!Complete) throw new InvalidOperationException("rig is not complete"); return _body; } }

        /// <summary>Adds the next chunk (its data is bin bytes [dataOffset, dataOffset + dataLength) of buf); true once the
        /// body is complete. bad_field if it does not continue the sequence or the body would exceed the limit.</summary>
        public bool Add(RigChunkHeader h, byte[] buf)
        {
            string problems = "";
            if (Complete) problems += "; a rig chunk after the rig was complete";
            if (h.Chunk != _received) problems += "; chunk " + h.Chunk + " arrived, expected " + _received;
            if (_chunks >= 0 && (h.Chunks != _chunks || h.Size != _size)) problems += "; chunks " + h.Chunks + " / size " + h.Size + " differ from the first chunk's";
            if (h.Offset != _next) problems += "; offset " + h.Offset + " != " + _next;
            long end = (long)h.Offset + h.DataLength;
            if (end > h.Size || (h.Chunk == h.Chunks - 1 && end != h.Size)) problems += "; chunk ends at byte " + end + " of a " + h.Size + "-byte rig";
            if (h.Size > ParamsProtocol.MaxRigBytes) problems += "; a rig of " + h.Size + " bytes exceeds the limit of " + ParamsProtocol.MaxRigBytes;
            if (problems.Length > 0) throw new ProtocolException(ErrorCodes.BadField, "bad rig chunk: " + problems.Substring(2));
            if (_body == null) _body = new byte[h.Size];
            Buffer.BlockCopy(buf, h.DataOffset, _body, h.Offset, h.DataLength);
            _chunks = h.Chunks; _size = h.Size; _received++;
            _next = (int)end;
            return Complete;
        }
    }

    /// <summary>Header of one `rig` message: body bytes [Offset, Offset + DataLength) of Size, chunk Chunk of Chunks.</summary>
    public struct RigChunkHeader
    {
        public int Chunk, Chunks, Size, Offset, DataOffset, DataLength;
        /// <summary>Rooms: whose avatar the rig deforms (null: the session's own).</summary>
        public string Member;
    }

    /// <summary>Decodes a rig body (strict: the checks and codes of ofera_protocol.rig.decode_rig).</summary>
    public sealed class RigDecoder : MessageDecoderBase
    {
        static readonly string[] Bindings = { "triangle", "barycentric" };

        readonly int[] _off = new int[RigGpuWords.Sections], _len = new int[RigGpuWords.Sections];

        public RigData Decode(byte[] body, int offset, int count)
        {
            const string w = "rig";
            Begin(body, offset, count, ParamsProtocol.MaxRigBytes);
            RigData r = new RigData();
            r.Binding = GetChoice(Top, Keys.Binding, w, Bindings, ErrorCodes.BadField, null) == "triangle" ? RigBinding.Triangle : RigBinding.Barycentric;
            long n = GetInt(Top, Keys.Count, w, 0, Protocol.UInt32Max);
            long s = GetInt(Top, Keys.Vertices, w, 0, Protocol.UInt32Max), u = GetInt(Top, Keys.Faces, w, 0, Protocol.UInt32Max);
            long m = GetInt(Top, Keys.Gaussians, w, 0, n);
            long e = GetInt(Top, Keys.ExprDims, w, 0, 256);
            int po, p;
            GetBin(Top, Keys.PoseRows, w, true, out po, out p);
            const int j = ParamsProtocol.Joints;
            Section(RigGpuWords.Index, Keys.Index, 4, m, "uint32", false);
            Section(RigGpuWords.Joints, Keys.JointsKey, 4, j * 3, "float32", true);
            Section(RigGpuWords.JointsExpr, Keys.JointsExpr, 4, j * 3 * e, "float32", true);
            Section(RigGpuWords.Template, Keys.Template, 4, s * 3, "float32", true);
            Section(RigGpuWords.ExprBasis, Keys.ExprBasis, 4, s * e * 3, "float32", true);
            Section(RigGpuWords.PoseRows, Keys.PoseRows, 1, p, "uint8", false);
            Section(RigGpuWords.PoseBasis, Keys.PoseBasis, 2, s * p * 3, "float16", true);
            Section(RigGpuWords.Weights, Keys.Weights, 4, s * j, "float32", true);
            Section(RigGpuWords.Face, Keys.Face, 4, u * 3, "uint32", false);
            Section(RigGpuWords.GaussianFace, Keys.GaussianFace, 4, m, "uint32", false);
            bool tri = r.Binding == RigBinding.Triangle;
            Section(RigGpuWords.Local, tri ? Keys.LocalPosition : Keys.Bary, 4, m * 3, "float32", true);
            if (tri) { _off[RigGpuWords.NormalOffset] = 0; _len[RigGpuWords.NormalOffset] = 0; }
            else Section(RigGpuWords.NormalOffset, Keys.NormalOffset, 4, m, "float32", true);
            Section(RigGpuWords.LocalRotation, Keys.LocalRotation, 2, m * 4, "float16", true);
            Section(RigGpuWords.LocalScale, Keys.LocalScale, 2, m * 3, "float16", true);

            byte[] b = R.Buffer;
            r.Count = (int)Math.Min(n, int.MaxValue); r.Vertices = (int)s; r.Faces = (int)u; r.Gaussians = (int)m;
            r.ExprDims = (int)e; r.PoseCount = p;
            r.Index = U32(b, RigGpuWords.Index);
            r.Joints = F32(b, RigGpuWords.Joints);
            r.JointsExpr = F32(b, RigGpuWords.JointsExpr);
            r.Template = F32(b, RigGpuWords.Template);
            r.ExprBasis = F32(b, RigGpuWords.ExprBasis);
            r.PoseRows = new byte[p];
            Buffer.BlockCopy(b, po, r.PoseRows, 0, p);
            r.PoseBasis = F16(b, RigGpuWords.PoseBasis);
            r.Weights = F32(b, RigGpuWords.Weights);
            r.Face = I32(b, RigGpuWords.Face);
            r.GaussianFace = I32(b, RigGpuWords.GaussianFace);
            r.Local = F32(b, RigGpuWords.Local);
            r.NormalOffset = tri ? null : F32(b, RigGpuWords.NormalOffset);
            r.LocalRotation = F16(b, RigGpuWords.LocalRotation);
            r.LocalScale = F16(b, RigGpuWords.LocalScale);

            string problems = "";
            if (m > 0 && r.Index[m - 1] >= (ulong)n) problems += "; 'index' holds " + r.Index[m - 1] + ", the avatar has " + n + " Gaussians";
            for (long i = 1; i < m; i++) if (r.Index[i] <= r.Index[i - 1]) { problems += "; 'index' is not strictly ascending"; break; }
            bool rowsOk = true;
            for (int i = 0; i < p; i++) if (r.PoseRows[i] >= ParamsProtocol.PoseFeature || (i > 0 && r.PoseRows[i] <= r.PoseRows[i - 1])) rowsOk = false;
            if (!rowsOk) problems += "; 'pose_rows' must be strictly ascending entries below " + ParamsProtocol.PoseFeature;
            uint worst = MaxU(r.Face);
            if (u > 0 && worst >= s) problems += "; 'face' indexes vertex " + worst + " of " + s;
            worst = MaxU(r.GaussianFace);
            if (m > 0 && worst >= u) problems += "; 'gaussian_face' indexes face " + worst + " of " + u;
            if (problems.Length > 0) throw Err(ErrorCodes.BadField, "rig: " + problems.Substring(2));
            r.Gpu = Words(b);
            return r;
        }

        void Section(int section, int key, int elemSize, long elements, string dtype, bool finite)
        {
            GetArray(Top, key, "rig", elemSize, elements, true, out _off[section], dtype);
            _len[section] = (int)(elements * elemSize);
            if (!finite) return;
            byte[] b = R.Buffer;
            int off = _off[section];
            bool ok = true;
            if (elemSize == 4) { for (long i = 0; i < elements && ok; i++) ok = (BitCast.ReadUInt32LE(b, (int)(off + 4 * i)) & 0x7f800000u) != 0x7f800000u; }
            else { for (long i = 0; i < elements && ok; i++) ok = (b[off + 2 * i + 1] & 0x7c) != 0x7c; }
            if (!ok) throw Err(ErrorCodes.NonFinite, "rig: field '" + Keys.Names[key] + "' holds NaN or infinity");
        }

        /// <summary>Largest value of a uint32 array held as int.</summary>
        static uint MaxU(int[] a)
        {
            uint v = 0;
            for (int i = 0; i < a.Length; i++) if ((uint)a[i] > v) v = (uint)a[i];
            return v;
        }

        float[] F32(byte[] b, int section)
        {
            float[] a = new float[_len[section] / 4];
            FrameCodec.DecodeF32(b, _off[section], a.Length, a, 0);
            return a;
        }

        float[] F16(byte[] b, int section)
        {
            float[] a = new float[_len[section] / 2];
            FrameCodec.DecodeF16(b, _off[section], a.Length, a, 0);
            return a;
        }

        uint[] U32(byte[] b, int section)
        {
            uint[] a = new uint[_len[section] / 4];
            for (int i = 0; i < a.Length; i++) a[i] = BitCast.ReadUInt32LE(b, _off[section] + 4 * i);
            return a;
        }

        /// <summary>uint32 arrays of indices as int (values of 2^31 and above become negative: the checks catch them).</summary>
        int[] I32(byte[] b, int section)
        {
            int[] a = new int[_len[section] / 4];
            for (int i = 0; i < a.Length; i++) a[i] = (int)BitCast.ReadUInt32LE(b, _off[section] + 4 * i);
            return a;
        }

        RigGpuWords Words(byte[] b)
        {
            RigGpuWords g = new RigGpuWords();
            int words = 0;
            for (int i = 0; i < RigGpuWords.Sections; i++) { g.Word[i] = words; words += (_len[i] + 3) / 4; }
            g.Words = new uint[Math.Max(words, 1)];
            for (int i = 0; i < RigGpuWords.Sections; i++)
            {
                if (_len[i] == 0) continue;
                if (BitConverter.IsLittleEndian) { Buffer.BlockCopy(b, _off[i], g.Words, 4 * g.Word[i], _len[i]); continue; }
                for (int k = 0; k < _len[i]; k++) g.Words[g.Word[i] + k / 4] |= (uint)b[_off[i] + k] << (8 * (k % 4));
            }
            return g;
        }
    }
    /// <summary>The params-session messages of ServerMessageDecoder (Codec.cs): `rig` chunks and params frames.</summary>
    public sealed partial class ServerMessageDecoder
    {
        /// <summary>`rig` (PROTOCOL.md 13.2): header and the position of its data in the input buffer.</summary>
        RigChunkHeader DecodeRigChunk()
        {
            const string w = "rig";
            RigChunkHeader h = new RigChunkHeader();
            long chunks = GetInt(Top, Keys.Chunks, w, 1, Protocol.UInt32Max);
            long size = GetInt(Top, Keys.Size, w, 0, Protocol.UInt32Max);
            h.Member = GetMember(Top, w, false);
            h.Chunk = (int)Math.Min(GetInt(Top, Keys.Chunk, w, 0, chunks - 1), int.MaxValue);
            long offset = GetInt(Top, Keys.Offset, w, 0, size);
            GetBin(Top, Keys.Data, w, true, out h.DataOffset, out h.DataLength);
            if (size > ParamsProtocol.MaxRigBytes)
                throw Err(ErrorCodes.BadField, "rig: a rig of " + size + " bytes exceeds the limit of " + ParamsProtocol.MaxRigBytes);
            h.Chunks = (int)Math.Min(chunks, int.MaxValue);
            h.Size = (int)size;
            h.Offset = (int)offset;
            return h;
        }

        /// <summary>A params frame (PROTOCOL.md 13.5): `seq` and `t` together or neither, `timing` only with them,
        /// `params` 68 finite float32. The values go to f.Params (HasParams); no Gaussians (N = 0, HasValues false).</summary>
        void DecodeParamsFrame(FrameData f)
        {
            const string w = "frame";
            long? seq = GetOptInt(Top, Keys.Seq, w, 0, long.MaxValue);
            long? t = GetOptInt(Top, Keys.T, w, long.MinValue, long.MaxValue);
            if (seq.HasValue != t.HasValue) throw Err(ErrorCodes.BadField, "frame: a params frame carries 'seq' and 't' together or neither");
            f.TimingCount = 0;
            if (Present(Top, Keys.Timing))
            {
                if (!seq.HasValue) throw Err(ErrorCodes.BadField, "frame: 'timing' on a params frame without 'seq' and 't'");
                DecodeTiming(f);
            }
            int off;
            GetArray(Top, Keys.Params, w, 4, ParamsProtocol.Length, true, out off, "float32");
            if (!FrameCodec.DecodeF32(R.Buffer, off, ParamsProtocol.Length, f.Params, 0))
                throw Err(ErrorCodes.NonFinite, "frame: field 'params' holds NaN or infinity");
            f.Seq = seq ?? 0;
            f.T = t ?? 0;
            f.Stamped = seq.HasValue;
            f.HasParams = true;
            f.N = 0;
            f.HasIndex = false;
            f.IsKey = false;
            f.HasValues = false;
            f.Payload.Length = 0;
        }
    }
}
