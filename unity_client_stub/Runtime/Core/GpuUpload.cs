// What the GPU upload path needs from the core: a frame's wire payload kept as it arrived (FramePayload,
// the bytes GaussianSplattingSink copies into a GraphicsBuffer once per frame), the q13 decode tables the
// kernel reads (uploaded once per session), and the CPU reference of the kernel (UgsPacking.WriteFrame:
// the same bytes, tested against the kernel on lavapipe by tests/test_unity_kernels.py).
// UnityEngine-free, C# 7.2.
using System;

namespace Ofera.Client
{
    /// <summary>
    /// One frame's arrays exactly as they arrived: [index (sparse frames only)][position][rotation][scale],
    /// each section copied byte for byte from its msgpack bin and starting on a 4-byte boundary (zero
    /// padding), so the buffer can be bound as 32-bit words. The word offsets locate the sections.
    /// The byte array grows to the largest frame and is reused (no per-frame allocation).
    /// </summary>
    public sealed class FramePayload
    {
        public byte[] Bytes = new byte[0];
        /// <summary>Bytes in use (a multiple of 4).</summary>
        public int Length;
        public int N;
        public bool HasIndex;
        public FrameEncoding Encoding;
        public int IndexWord, PositionWord, RotationWord, ScaleWord;

        public int Words { get { return Length >> 2; } }

        static int Pad4(int n) { return (n + 3) & ~3; }

        internal void Fill(byte[] src, FrameEncoding enc, int n, bool hasIndex, int idxOff,
                           int pOff, int pLen, int rOff, int rLen, int sOff, int sLen)
        {
            int iLen = hasIndex ? 4 * n : 0;
            int total = Pad4(iLen) + Pad4(pLen) + Pad4(rLen) + Pad4(sLen);
            if (Bytes.Length < total) Bytes = new byte[Math.Max(total, Bytes.Length * 2)];
            N = n; HasIndex = hasIndex; Encoding = enc;
            int at = 0;
            IndexWord = 0;
            if (hasIndex) at = Copy(src, idxOff, iLen, at);
            PositionWord = at >> 2; at = Copy(src, pOff, pLen, at);
            RotationWord = at >> 2; at = Copy(src, rOff, rLen, at);
            ScaleWord = at >> 2; at = Copy(src, sOff, sLen, at);
            Length = at;
        }

        int Copy(byte[] src, int off, int len, int at)
        {
            Buffer.BlockCopy(src, off, Bytes, at, len);
            int end = Pad4(at + len);
            for (int i = at + len; i < end; i++) Bytes[i] = 0;
            return end;
        }

        public void CopyFrom(FramePayload o)
        {
            if (Bytes.Length < o.Length) Bytes = new byte[o.Length];
            Buffer.BlockCopy(o.Bytes, 0, Bytes, 0, o.Length);
            Length = o.Length; N = o.N; HasIndex = o.HasIndex; Encoding = o.Encoding;
            IndexWord = o.IndexWord; PositionWord = o.PositionWord; RotationWord = o.RotationWord; ScaleWord = o.ScaleWord;
        }
    }

    public static class GpuTables
    {
        public const int PositionLevels = 65536;

        /// <summary>
        /// q13 position table for the kernel: 3 x 65536 float32 (x levels, then y, then z), each
        /// pos_min + q (pos_max - pos_min) / 65535 computed exactly as FrameCodec.DecodeQ13Positions.
        /// </summary>
        public static float[] Q13Positions(Quant quant)
        {
            float[] t = new float[3 * PositionLevels];
            for (int a = 0; a < 3; a++)
            {
                double lo = quant.PosMin[a];
                double step = (quant.PosMax[a] - lo) / FrameCodec.PosLevels;
                for (int q = 0; q < PositionLevels; q++) t[a * PositionLevels + q] = (float)(lo + q * step);
            }
            return t;
        }

        /// <summary>q13 scale table for the kernel: the 256 values of <see cref="Quant.ScaleTable"/>.</summary>
        public static float[] Q13Scales(Quant quant) { return quant.ScaleTable; }

        /// <summary>The kernel's entry point for an encoding.</summary>
        public static string KernelName(FrameEncoding e)
        {
            return e == FrameEncoding.Q13 ? "CSOferaDecodeQ13" : e == FrameEncoding.F16 ? "CSOferaDecodeF16" : "CSOferaDecodeF32";
        }

        /// <summary>serverToGpu (-1 unmatched) as the kernel's uint table (0xffffffff unmatched).</summary>
        public static uint[] PermutationWords(int[] serverToGpu)
        {
            uint[] w = new uint[Math.Max(1, serverToGpu.Length)];
            for (int i = 0; i < serverToGpu.Length; i++) w[i] = serverToGpu[i] < 0 ? 0xffffffffu : (uint)serverToGpu[i];
            return w;
        }

        /// <summary>The avatar's neutral state as a dense f32 payload (the first state written at session start; little-endian hosts).</summary>
        public static void NeutralPayload(AvatarData a, FramePayload dst)
        {
            int n = a.Count;
            byte[] tmp = new byte[40 * Math.Max(1, n)];
            Buffer.BlockCopy(a.Position, 0, tmp, 0, 12 * n);
            Buffer.BlockCopy(a.Rotation, 0, tmp, 12 * n, 16 * n);
            Buffer.BlockCopy(a.Scale, 0, tmp, 28 * n, 12 * n);
            dst.Fill(tmp, FrameEncoding.F32, n, false, 0, 0, 12 * n, 12 * n, 16 * n, 28 * n, 12 * n);
        }
    }
}
