"""The Grbl host's hold watch: a ``!`` the board did not take is sent again, and only then."""

from __future__ import annotations

from server.backends.grbl.holdwatch import RESENDS, HoldWatch, Verdict


def test_a_hold_is_judged_on_the_second_poll_after_it_and_sent_again_while_the_board_runs(
) -> None:
    watch = HoldWatch()
    assert watch.report("Run", 5) is Verdict.WAIT, "nothing asked: nothing to watch"
    watch.asked(polls_sent=5)
    assert watch.report("Run", 6) is Verdict.WAIT, "the first poll after it may predate it"
    assert watch.report("Run", 7) is Verdict.RESEND
    watch.asked(polls_sent=8, again=True)
    assert watch.report("Run", 9) is Verdict.WAIT
    assert watch.report("Hold:1", 10) is Verdict.WAIT
    assert watch.report("Run", 20) is Verdict.WAIT, "it held: the watch ended"


def test_other_states_a_resume_and_a_reset_end_the_watch() -> None:
    for state in ("Hold:0", "Jog", "Home", "Idle", "Alarm", "Door:0"):
        watch = HoldWatch()
        watch.asked(polls_sent=0)
        assert watch.report(state, 2) is Verdict.WAIT
        assert watch.report("Run", 4) is Verdict.WAIT, state
    watch = HoldWatch()
    watch.asked(polls_sent=0)
    watch.clear()
    assert watch.report("Run", 4) is Verdict.WAIT


def test_a_board_that_never_holds_is_given_up_after_a_few_resends_and_a_new_hold_counts_afresh(
) -> None:
    watch = HoldWatch()
    watch.asked(polls_sent=0)
    verdicts = []
    for poll in range(2, 40):
        verdict = watch.report("Run", poll)
        verdicts.append(verdict)
        if verdict is Verdict.RESEND:
            watch.asked(polls_sent=poll, again=True)
    assert verdicts.count(Verdict.RESEND) == RESENDS
    assert verdicts.count(Verdict.GIVE_UP) == 1
    assert verdicts[-1] is Verdict.WAIT
    watch.asked(polls_sent=50)
    assert watch.report("Run", 52) is Verdict.RESEND
