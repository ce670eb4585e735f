

def test_validation_split_holds_out_every_kth_from_the_middle():
    from ctgs.scene.loader import validation_split

    views = list(range(10))
    assert validation_split(views, 4) == ([0, 1, 3, 4, 5, 7, 8, 9], [2, 6])
    assert validation_split(views, 0) == (views, [])
    train, val = validation_split(views, 8)
    assert val == [4] and len(train) == 9
