// The C# core's side of tests/test_unity_rig_kernel.py: assembles and decodes a rig body the way a params session does
// (RigAssembler, RigDecoder) and writes what the Unity sink uploads (RigGpuWords: the words and their section offsets)
// and the C# reference deformation (RigDeformer) of each frame's params.
// Usage: mono RigGpuReference.exe DIR FRAMES; DIR holds rig.bin (the body) and params.bin (FRAMES x 68 float32); writes
// words.bin (uint32), words.hdr (14 int32 section offsets), position/rotation/scale<i>.bin (float32). C# 7.2.
using System;
using System.IO;
using Ofera.Client;

static class RigGpuReference
{
    static void Write(string path, Array a, int bytes)
    {
        byte[] b = new byte[bytes];
        Buffer.BlockCopy(a, 0, b, 0, bytes);
        File.WriteAllBytes(path, b);
    }

    static int Main(string[] args)
    {
        string dir = args[0];
        int frames = int.Parse(args[1]);
        byte[] body = File.ReadAllBytes(Path.Combine(dir, "rig.bin"));
        RigAssembler parts = new RigAssembler();
        int half = body.Length / 2; // two chunks, as a server may cut it
        parts.Add(new RigChunkHeader { Chunk = 0, Chunks = 2, Size = body.Length, Offset = 0, DataOffset = 0, DataLength = half }, body);
        parts.Add(new RigChunkHeader { Chunk = 1, Chunks = 2, Size = body.Length, Offset = half, DataOffset = half, DataLength = body.Length - half }, body);
        RigData rig = new RigDecoder().Decode(parts.Body, 0, parts.Body.Length);
        Write(Path.Combine(dir, "words.bin"), rig.Gpu.Words, 4 * rig.Gpu.Words.Length);
        Write(Path.Combine(dir, "words.hdr"), rig.Gpu.Word, 4 * RigGpuWords.Sections);
        byte[] pb = File.ReadAllBytes(Path.Combine(dir, "params.bin"));
        float[] values = new float[pb.Length / 4];
        Buffer.BlockCopy(pb, 0, values, 0, pb.Length);
        int m = rig.Gaussians;
        float[] pos = new float[3 * m], rot = new float[4 * m], scl = new float[3 * m];
        RigDeformer d = new RigDeformer(rig);
        for (int k = 0; k < frames; k++)
        {
            d.Deform(values, k * ParamsProtocol.Length, pos, rot, scl);
            Write(Path.Combine(dir, "position" + k + ".bin"), pos, 4 * pos.Length);
            Write(Path.Combine(dir, "rotation" + k + ".bin"), rot, 4 * rot.Length);
            Write(Path.Combine(dir, "scale" + k + ".bin"), scl, 4 * scl.Length);
        }
        return 0;
    }
}
