// The C# core's side of tests/test_unity_kernels.py: decodes frames with ServerMessageDecoder (payload
// kept, as the GPU path does), and writes what the Unity uploader would upload (FramePayload words and
// section offsets, the q13 tables) and the CPU reference of the kernels (UgsPacking.Hide, WriteFrame).
// Usage: mono GpuReference.exe DIR FRAMES SPLATS MIRROR(0|1); DIR holds welcome.msgpack,
// frame<i>.msgpack and perm.bin (uint32 server->GPU, 0xffffffff unmatched). C# 7.2, no UnityEngine.
using System;
using System.IO;
using Ofera.Client;

static class GpuReference
{
    static void WriteWords(string path, uint[] w, int count)
    {
        byte[] b = new byte[4 * count];
        Buffer.BlockCopy(w, 0, b, 0, b.Length);
        File.WriteAllBytes(path, b);
    }

    static void WriteFloats(string path, float[] f)
    {
        byte[] b = new byte[4 * f.Length];
        Buffer.BlockCopy(f, 0, b, 0, b.Length);
        File.WriteAllBytes(path, b);
    }

    static int Main(string[] args)
    {
        string dir = args[0];
        int frames = int.Parse(args[1]), splats = int.Parse(args[2]);
        bool mirror = args[3] == "1";
        ServerMessageDecoder dec = new ServerMessageDecoder();
        dec.KeepPayload = true;
        ServerMessage msg = new ServerMessage();
        byte[] wb = File.ReadAllBytes(Path.Combine(dir, "welcome.msgpack"));
        if (dec.Decode(wb, 0, wb.Length, null, msg) != ServerMessageKind.Welcome) { Console.Error.WriteLine("not a welcome"); return 2; }
        FrameFormat fmt = msg.Welcome.ToFormat();
        byte[] pb = File.ReadAllBytes(Path.Combine(dir, "perm.bin"));
        int[] perm = new int[pb.Length / 4];
        for (int i = 0; i < perm.Length; i++)
        {
            uint v = BitConverter.ToUInt32(pb, 4 * i);
            perm[i] = v == 0xffffffffu ? -1 : (int)v;
        }
        if (fmt.Encoding == FrameEncoding.Q13)
        {
            WriteFloats(Path.Combine(dir, "pos_table.bin"), GpuTables.Q13Positions(fmt.Quant));
            WriteFloats(Path.Combine(dir, "scale_table.bin"), GpuTables.Q13Scales(fmt.Quant));
        }
        uint[] pos = new uint[3 * splats], other = new uint[4 * splats];
        UgsPacking.Hide(pos, other, splats);
        msg.Frame = new FrameData();
        for (int i = 0; i < frames; i++)
        {
            byte[] fb = File.ReadAllBytes(Path.Combine(dir, "frame" + i + ".msgpack"));
            if (dec.Decode(fb, 0, fb.Length, fmt, msg) != ServerMessageKind.Frame) { Console.Error.WriteLine("frame " + i + " is not a frame"); return 2; }
            FrameData f = msg.Frame;
            FramePayload p = f.Payload;
            File.WriteAllBytes(Path.Combine(dir, "payload" + i + ".bin"), SubArray(p.Bytes, p.Length));
            int[] hdr = { p.N, p.HasIndex ? 1 : 0, p.IndexWord, p.PositionWord, p.RotationWord, p.ScaleWord, p.Words };
            byte[] hb = new byte[4 * hdr.Length];
            Buffer.BlockCopy(hdr, 0, hb, 0, hb.Length);
            File.WriteAllBytes(Path.Combine(dir, "payload" + i + ".hdr"), hb);
            UgsPacking.WriteFrame(f, perm, mirror, pos, other);
            WriteWords(Path.Combine(dir, "cpu_pos" + i + ".bin"), pos, pos.Length);
            WriteWords(Path.Combine(dir, "cpu_other" + i + ".bin"), other, other.Length);
        }
        Console.WriteLine("ok " + frames + " frames, " + fmt.Encoding + (fmt.Sparse ? " sparse" : " dense"));
        return 0;
    }

    static byte[] SubArray(byte[] b, int n)
    {
        byte[] r = new byte[n];
        Buffer.BlockCopy(b, 0, r, 0, n);
        return r;
    }
}
