// Hand-written stand-ins for the few UnityEngine, Unity.Collections, GaussianSplatting (1.1.1 + Patches/),
// Meta XR SDK (68) members that Runtime/Unity's scripts use, so that run.sh can type-check those scripts
// without Unity. Signatures follow those versions; bodies do nothing. Catches C# mistakes, not API drift.
using System;
using System.Collections.Generic;
namespace UnityEngine {
  public class Object { public string name; public static void Destroy(Object o) {} public static T Instantiate<T>(T o, Transform parent) where T : Object { return o; }
    public static T FindAnyObjectByType<T>() where T : Object { return null; }
    public static bool operator ==(Object a, Object b) { return ReferenceEquals(a, b); } public static bool operator !=(Object a, Object b) { return !ReferenceEquals(a, b); }
    public override bool Equals(object o) { return ReferenceEquals(this, o); } public override int GetHashCode() { return 0; } }
  public class Component : Object { public GameObject gameObject; public Transform transform; public T GetComponent<T>() { return default(T); } public T[] GetComponentsInChildren<T>(bool inactive) { return null; } }
  public class Behaviour : Component { public bool enabled; public bool isActiveAndEnabled; }
  public class MonoBehaviour : Behaviour {}
  public sealed class GameObject : Object { public Transform transform; public T AddComponent<T>() where T : Component { return null; } public T[] GetComponentsInChildren<T>(bool inactive) { return null; } public T GetComponent<T>() { return default(T); } }
  public class Transform : Component { public Vector3 localPosition; public Quaternion localRotation; public void SetPositionAndRotation(Vector3 p, Quaternion q) {} public void GetPositionAndRotation(out Vector3 p, out Quaternion q) { p = default(Vector3); q = default(Quaternion); } }
  public struct Vector3 { public float x, y, z; public Vector3(float a, float b, float c) { x = a; y = b; z = c; } public static Vector3 zero; public static Vector3 operator +(Vector3 a, Vector3 b) { return a; } }
  public struct Quaternion { public static Quaternion identity; public static Vector3 operator *(Quaternion q, Vector3 v) { return v; } }
  public struct Color32 { public Color32(byte r, byte g, byte b, byte a) {} }
  public struct Bounds { public void Expand(float f) {} }
  public static class Debug { public static void Log(object o) {} public static void LogWarning(object o) {} public static void LogError(object o) {} }
  public static class Time { public static int frameCount; public static float unscaledTime, realtimeSinceStartup; }
  public static class Mathf { public static float Clamp01(float v) { return v; } public static int Clamp(int v, int a, int b) { return v; } public static int Min(int a, int b) { return a; } public static float Max(float a, float b) { return a; } public static float Sin(float a) { return a; } public static float Repeat(float a, float b) { return a; } }
  public sealed class Shader : Object { public static int PropertyToID(string n) { return 0; } public static Shader Find(string n) { return null; } }
  public sealed class ComputeShader : Object { public int FindKernel(string n) { return 0; } public void SetInt(int id, int v) {} public void SetBuffer(int k, int id, GraphicsBuffer b) {} public void Dispatch(int k, int x, int y, int z) {} }
  public sealed class GraphicsBuffer : IDisposable { public enum Target { Raw = 32 } [Flags] public enum UsageFlags { None = 0, LockBufferForWrite = 1 }
    public GraphicsBuffer(Target t, int count, int stride) {} public GraphicsBuffer(Target t, UsageFlags u, int count, int stride) {}
    public int count; public string name; public void SetData(Array a) {} public void SetData(Array a, int m, int g, int c) {} public void Release() {} public void Dispose() {}
    public Unity.Collections.NativeArray<T> LockBufferForWrite<T>(int start, int count) where T : struct { return default(Unity.Collections.NativeArray<T>); } public void UnlockBufferAfterWrite<T>(int n) where T : struct {} }
  public static class SystemInfo { public static bool supportsComputeShaders; public static Rendering.GraphicsDeviceType graphicsDeviceType; }
  public class TextAsset : Object { public long dataSize; public Unity.Collections.NativeArray<T> GetData<T>() where T : struct { return default(Unity.Collections.NativeArray<T>); } }
  public sealed class Material : Object { public Material(Shader s) {} public void SetFloat(string n, float v) {} }
  public sealed class Mesh : Object { public Rendering.IndexFormat indexFormat; public Bounds bounds; public void MarkDynamic() {} public void Clear() {} public void SetVertices(Vector3[] v) {} public void SetColors(Color32[] c) {} public void SetIndices(int[] i, MeshTopology t, int s, bool b) {} public void RecalculateBounds() {} }
  public enum MeshTopology { Points }
  public sealed class MeshFilter : Component { public Mesh sharedMesh; }
  public sealed class MeshRenderer : Component { public Material sharedMaterial; public Rendering.ShadowCastingMode shadowCastingMode; public bool receiveShadows; }
  public sealed class AddComponentMenu : Attribute { public AddComponentMenu(string s) {} }
  public sealed class DefaultExecutionOrder : Attribute { public DefaultExecutionOrder(int o) {} }
  public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string s) {} }
  public sealed class HeaderAttribute : Attribute { public HeaderAttribute(string s) {} }
  public sealed class RangeAttribute : Attribute { public RangeAttribute(float a, float b) {} }
  public sealed class RequireComponent : Attribute { public RequireComponent(Type a, Type b) {} }
}
namespace UnityEngine.Rendering { public enum IndexFormat { UInt32 } public enum ShadowCastingMode { Off }
  public enum GraphicsDeviceType { Direct3D11 = 2, Null = 4, OpenGLES3 = 11, Metal = 16, OpenGLCore = 17, Direct3D12 = 18, Vulkan = 21 } }
namespace Unity.Collections {
  public struct NativeArray<T> where T : struct { public int Length; public T[] ToArray() { return null; } public NativeArray<U> Reinterpret<U>(int size) where U : struct { return default(NativeArray<U>); }
    public static void Copy(T[] src, int si, NativeArray<T> dst, int di, int n) {} }
}
namespace GaussianSplatting.Runtime {
  public class GaussianSplatAsset : UnityEngine.Object { public enum VectorFormat { Float32, Norm16, Norm11, Norm6 } public enum SHFormat { Float32, Float16, Norm11, Norm6, Cluster64k }
    public int splatCount; public VectorFormat posFormat, scaleFormat; public SHFormat shFormat; public UnityEngine.TextAsset posData, otherData, shData, chunkData; }
  public class GaussianSplatRenderer : UnityEngine.MonoBehaviour { public GaussianSplatAsset asset; public UnityEngine.GraphicsBuffer gpuPosData, gpuOtherData, gpuSHData; public event Action<GaussianSplatRenderer> gpuResourcesCreated; }
}
public static class OVRPlugin { public enum Step { Render = -1 } public struct FaceExpressionStatus { public bool IsValid; }
  public struct FaceState { public float[] ExpressionWeights; public float[] ExpressionWeightConfidences; public FaceExpressionStatus Status; public double Time; }
  public static bool GetFaceState2(Step s, int f, ref FaceState st) { return false; } public static bool GetFaceState(Step s, int f, ref FaceState st) { return false; } }
public class OVRFaceExpressions : UnityEngine.MonoBehaviour { public enum FaceExpression { Max = 70 } public enum FaceRegionConfidence { Lower, Upper, Max } public enum FaceTrackingDataSource { Visual, Audio }
  public bool TryGetFaceTrackingDataSource(out FaceTrackingDataSource s) { s = 0; return false; } }
namespace Ofera.Client.Unity { public interface IFaceSampleTime { bool TryGetSampleTime(out double seconds); } }
