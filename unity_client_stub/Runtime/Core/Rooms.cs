// Several avatars in one session (rooms, PROTOCOL.md 12): the newest-frame handoff per member between the receive
// thread and the main thread, and the room events the main thread spawns and removes renderers from.
// UnityEngine-free, C# 7.2.
using System.Collections.Generic;

namespace Ofera.Client
{
    public enum RoomEventKind { Joined, Left }

    /// <summary>A member whose avatar is complete (Joined: spawn a renderer), a watch-only member who joined (Joined with
    /// Avatar null: nothing to show), or a member who left (Left: remove it).</summary>
    public sealed class RoomEvent
    {
        public RoomEventKind Kind;
        public string Member;
        /// <summary>Joined: the member's static avatar (session coordinates), null for a watch-only member; Left: null.</summary>
        public AvatarData Avatar;
        public JoinMessage Join;
        /// <summary>Joined (publishing): the session's welcome with this member's avatar (what a sink's SetAvatar needs).</summary>
        public Welcome Welcome;
        /// <summary>Left: the server's reason: bye, closed, server_gone or stale (PROTOCOL.md 12.4).</summary>
        public string Reason;
        /// <summary>Session number (OferaClient.SessionNumber) the event belongs to; members of older sessions are gone.</summary>
        public int Session;

        public override string ToString() { return Kind + " " + Member + (Reason != null ? " (" + Reason + ")" : ""); }
    }

    /// <summary>
    /// Newest-wins frame handoff, one slot per member (null: the session's own avatar, v1), sharing one
    /// pool of <see cref="FrameData"/>. The receive thread decodes into <see cref="DecodeTarget"/> and
    /// calls <see cref="Publish"/>; the main thread calls <see cref="Take"/>, and the frame it gets stays
    /// valid until its next Take for that member. No allocation once every slot has its frames, across joins,
    /// leaves and new sessions too: a departed member's held frame (which the main thread may still be reading
    /// when the receive thread drops the member) is parked, and returns to the pool when the main thread is done
    /// with it: its next Take for that member id, <see cref="Release"/> (OferaClient calls it when the main thread
    /// takes the member's Left event) or <see cref="ReleaseBefore"/> (an event or avatar of a newer session).
    /// </summary>
    public sealed class FrameExchange
    {
        sealed class Slot
        {
            public FrameData Ready, Held;
        }

        struct Parked
        {
            public string Member;  // null: the session's own avatar
            public int Session;
            public FrameData Frame;
        }

        readonly object _lock = new object();
        readonly Stack<FrameData> _pool = new Stack<FrameData>();
        readonly Dictionary<string, Slot> _members = new Dictionary<string, Slot>();
        readonly Slot _own = new Slot();
        readonly List<Parked> _parked = new List<Parked>();
        FrameData _rx = new FrameData();
        int _session, _allocated = 1;

        /// <summary>Receive thread only: the container the next frame is decoded into.</summary>
        public FrameData DecodeTarget { get { return _rx; } }

        /// <summary>Frames currently pooled (tests).</summary>
        public int Pooled { get { lock (_lock) return _pool.Count; } }

        /// <summary>FrameData objects this exchange has created so far (tests: flat once every slot has its frames).</summary>
        public int Allocated { get { lock (_lock) return _allocated; } }

        /// <summary>Held frames of departed members not yet returned to the pool (tests).</summary>
        public int ParkedCount { get { lock (_lock) return _parked.Count; } }

        /// <summary>Receive thread: hands the frame in DecodeTarget to its member's slot. True if an untaken frame was replaced (dropped).</summary>
        public bool Publish(string member)
        {
            lock (_lock)
            {
                Slot s = SlotFor(member, true);
                bool dropped = s.Ready != null;
                FrameData next = dropped ? s.Ready : _pool.Count > 0 ? _pool.Pop() : NewFrame();
                s.Ready = _rx;
                _rx = next;
                return dropped;
            }
        }

        /// <summary>Receive thread: whether the member's slot holds a frame the main thread has not taken (the next
        /// Publish would replace it).</summary>
        public bool HasUntaken(string member)
        {
            lock (_lock)
            {
                Slot s = SlotFor(member, false);
                return s != null && s.Ready != null;
            }
        }

        /// <summary>Main thread: the member's newest frame not taken yet, or null. Recycles the one taken before.</summary>
        public FrameData Take(string member)
        {
            lock (_lock)
            {
                if (_parked.Count > 0) ReleaseWhere(member, false, 0);  // its earlier life's frame: done with it too
                Slot s = SlotFor(member, false);
                if (s == null) return null;
                if (s.Held != null) { _pool.Push(s.Held); s.Held = null; }
                if (s.Ready == null) return null;
                s.Held = s.Ready;
                s.Ready = null;
                return s.Held;
            }
        }

        /// <summary>Receive thread, on leave: forgets the member. Its untaken frame returns to the pool; the one the
        /// main thread holds is parked (the main thread may finish with it) until <see cref="Release"/>, the next
        /// Take for that id, or <see cref="ReleaseBefore"/> a newer session.</summary>
        public void Drop(string member)
        {
            lock (_lock)
            {
                Slot s;
                if (member == null || !_members.TryGetValue(member, out s)) return;
                if (s.Ready != null) _pool.Push(s.Ready);
                Park(member, s.Held);
                _members.Remove(member);
            }
        }

        /// <summary>New session (receive thread): untaken frames of every slot return to the pool; members are
        /// forgotten and their held frames parked until the main thread sees the new session
        /// (<see cref="ReleaseBefore"/>) or takes that id again. The own slot keeps its held frame (recycled by
        /// the next Take(null), as always).</summary>
        public void Reset() { Reset(_session + 1); }

        /// <summary>As <see cref="Reset()"/>, numbering the new session (OferaClient: its SessionNumber).</summary>
        public void Reset(int session)
        {
            lock (_lock)
            {
                if (_own.Ready != null) { _pool.Push(_own.Ready); _own.Ready = null; }
                foreach (KeyValuePair<string, Slot> kv in _members)
                {
                    if (kv.Value.Ready != null) _pool.Push(kv.Value.Ready);
                    Park(kv.Key, kv.Value.Held);
                }
                _members.Clear();
                _session = session;
            }
        }

        /// <summary>Main thread: done with a departed member's last frame (OferaClient calls this as the main thread
        /// takes the member's Left event): it returns to the pool.</summary>
        public void Release(string member)
        {
            if (member == null) return;
            lock (_lock) ReleaseWhere(member, false, 0);
        }

        /// <summary>Main thread: it has seen session <paramref name="session"/> (an event or avatar of it): the held
        /// frames of members of older sessions return to the pool.</summary>
        public void ReleaseBefore(int session)
        {
            lock (_lock) ReleaseWhere(null, true, session);
        }

        void Park(string member, FrameData held)
        {
            if (held == null) return;
            Parked p;
            p.Member = member; p.Session = _session; p.Frame = held;
            _parked.Add(p);
        }

        void ReleaseWhere(string member, bool bySession, int session)
        {
            for (int i = _parked.Count - 1; i >= 0; i--)
            {
                Parked p = _parked[i];
                if (bySession ? p.Session < session : p.Member == member)
                {
                    _pool.Push(p.Frame);
                    _parked.RemoveAt(i);
                }
            }
        }

        FrameData NewFrame()
        {
            _allocated++;
            return new FrameData();
        }

        Slot SlotFor(string member, bool create)
        {
            if (member == null) return _own;
            Slot s;
            if (_members.TryGetValue(member, out s)) return s;
            if (!create) return null;
            s = new Slot();  // one per member join (small, no frame data)
            _members[member] = s;
            return s;
        }
    }
}
